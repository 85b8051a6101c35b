"""
Where the planner's time goes that the matmul roofline does not show, measured part by part in one process
(each pair of alternatives interleaved over ``--rounds`` rounds; the median per-round ratio is reported, so the
drift of a shared machine affects both sides alike). Adds one row per part to benchmarks/RESULTS.md.

    python benchmarks/speed/planner_parts.py [--threads 2] [--rounds 15]

Parts, at the paper setting's sizes:

1. CEM sampling, one iteration of POPLIN-P Sep (500 candidates x 23,220 dims): one serial torch generator filling
   the whole candidate buffer then scaling it in place (the planner until 2026-12-01), against the planner's
   chunked sampling (SFC64 streams per chunk of rows, scaled while in cache, chunks shared among the threads).
2. One 500 x 200 x 200 layer as a oneDNN linear, with and without the fused SiLU, fp32 and bf16: the SiLU costs the
   same time in both dtypes, which bounds the bf16 speed-up of the 200-wide layers.
3. One expectation forward of the 5 x 4 x 200 ensemble on 500 rows (one env) and on 1000 rows (two envs planned
   in one batch) at the given thread count: oneDNN's own threads splitting each product, against one
   single-threaded share of the members x rows per thread.
4. CEM elite statistics of one POPLIN-P Sep iteration (50 elites x 23,220 dims): element-wise weighting and
   reductions over the elites (the planner until 2026-12-01), against the planner's [1, K] x [K, D] products.
5. The expectation forward at the CPU budget's sizes (5 members of 3 x 64, 3 x 128 and 4 x 200, 100-1000 rows): the
   fused per-member oneDNN layers against the batched matmuls, the ratio behind ``kernels.FUSED_MIN_ROWS``.

    python benchmarks/speed/planner_parts.py --threads 1 --parts 5
"""

from __future__ import annotations

import argparse
import datetime
import functools
import os
import statistics
import sys
import time
from collections.abc import Callable

import torch as th

from sb3_poplin import kernels
from sb3_poplin.dynamics import ProbabilisticEnsemble
from sb3_poplin.kernels import ParameterCache, onednn_fused_linear
from sb3_poplin.sampling import CandidateSampler, Workspace, run_shares, split_range, truncated_normal

# benchmarks/, where results_file.py (shared by the scripts of every subfolder) lives
sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
from results_file import append_row, describe_machine


def interleave(alternatives: dict[str, Callable[[], object]], rounds: int, inner: int) -> dict[str, list[float]]:
    """Seconds per call of each alternative, ``rounds`` rounds of ``inner`` calls each, alternatives in turn."""
    samples: dict[str, list[float]] = {name: [] for name in alternatives}
    for fn in alternatives.values():
        fn()  # warm-up
    for _ in range(rounds):
        for name, fn in alternatives.items():
            start = time.perf_counter()
            for _ in range(inner):
                fn()
            samples[name].append((time.perf_counter() - start) / inner)
    return samples


def summary(samples: dict[str, list[float]], baseline: str) -> str:
    parts = []
    for name, values in samples.items():
        text = f"{name} {statistics.median(values) * 1e3:.2f} ms"
        if name != baseline:
            ratio = statistics.median(b / a for a, b in zip(samples[baseline], values, strict=True))
            text += f" ({ratio:.2f}x {baseline})"
        parts.append(text)
    return "; ".join(parts)


def split_rows(members: int, rows: int, shares: int) -> list[list[tuple[int, int, int]]]:
    """The members x rows cut into ``shares`` contiguous member-major pieces: per share its (member, start, stop)."""
    plan = []
    for lo, hi in split_range(members * rows, shares):
        pieces = []
        while lo < hi:
            member, start = divmod(lo, rows)
            stop = min(hi - member * rows, rows)
            pieces.append((member, start, stop))
            lo = member * rows + stop
        plan.append(pieces)
    return plan


def sampling_part(rounds: int) -> str:
    pop, dim = 500, 30 * 774
    mean, std = th.zeros(1, dim), th.full((1, dim), 0.1)
    sampler = CandidateSampler(pop)
    generator = th.Generator().manual_seed(0)
    store = Workspace()

    def serial() -> th.Tensor:
        out = store.get("samples", pop * dim, th.float32, mean.device).view(1, pop, dim)
        bits = store.get("bits", (pop * dim + 3) // 4, th.int64, mean.device)
        truncated_normal(out.shape, mean.device, generator, out=out, scratch=bits, unit_variance=False)
        return th.addcmul(mean.unsqueeze(1), out, std.unsqueeze(1), out=out)

    def chunked() -> th.Tensor:
        return sampler.sample(mean, std, generator)

    samples = interleave({"serial torch generator": serial, "chunked SFC64": chunked}, rounds, 1)
    per_sample = statistics.median(samples["chunked SFC64"]) / (pop * dim) * 1e9
    return summary(samples, "serial torch generator") + f"; {per_sample:.2f} ns per sample"


def layer_part(rounds: int) -> str:
    generator = th.Generator().manual_seed(0)
    x, w, b = (th.randn(shape, generator=generator) for shape in ((500, 200), (200, 200), (200,)))
    alternatives = {}
    for dtype, label in ((th.float32, "fp32"), (th.bfloat16, "bf16")):
        linear = onednn_fused_linear(dtype)
        if linear is None:
            return "oneDNN's fused linear is not available in this torch build"
        xd, wd, bd = x.to(dtype), w.to(dtype), b.to(dtype)
        for post, name in (("none", "linear"), ("swish", "linear+SiLU")):
            alternatives[f"{label} {name}"] = functools.partial(linear, xd, wd, bd, post, [], "")
    samples = interleave(alternatives, rounds, 50)
    flops = 2 * 500 * 200 * 200
    silu = {
        label: (statistics.median(samples[f"{label} linear+SiLU"]) - statistics.median(samples[f"{label} linear"])) * 1e6
        for label in ("fp32", "bf16")
    }
    rates = ", ".join(f"{name} {flops / statistics.median(v) / 1e9:.0f} GFLOP/s" for name, v in samples.items())
    speedups = (
        f"bf16 speed-up: linear {statistics.median(samples['fp32 linear']) / statistics.median(samples['bf16 linear']):.2f}x, "
        f"linear+SiLU {statistics.median(samples['fp32 linear+SiLU']) / statistics.median(samples['bf16 linear+SiLU']):.2f}x"
    )
    return f"{rates}; SiLU adds {silu['fp32']:.0f} us (fp32) / {silu['bf16']:.0f} us (bf16); {speedups}"


def forward_part(rounds: int, threads: int, rows: int = 500) -> str:
    th.manual_seed(0)
    model = ProbabilisticEnsemble(17, 6, 5, (200, 200, 200, 200))
    x = th.randn(rows, model.in_dim)
    linear = onednn_fused_linear(th.float32)
    if linear is None:
        return "oneDNN's fused linear is not available in this torch build"
    layers = ParameterCache.layers(model, th.float32, "members")
    cols = model.out_dim

    def by_shares() -> th.Tensor:
        out = x.new_empty(model.ensemble_size, x.shape[0], cols)

        def share(pieces: list[tuple[int, int, int]]) -> Callable[[], None]:
            def run() -> None:
                for member, start, stop in pieces:
                    h = x[start:stop]
                    for weight, bias in layers[:-1]:
                        h = linear(h, weight[member], bias[member], "swish", [], "")
                    weight, bias = layers[-1]
                    out[member, start:stop] = linear(h, weight[member, :cols], bias[member, :cols], "none", [], "")

            return run

        run_shares([share(p) for p in split_rows(model.ensemble_size, x.shape[0], threads)])
        return out

    with th.inference_mode():
        samples = interleave({"oneDNN threads": lambda: model.shared_input_mean(x), "member shares": by_shares}, rounds, 20)
        assert th.allclose(model.shared_input_mean(x), by_shares(), atol=1e-5)
    flops = 2 * model.ensemble_size * rows * (model.in_dim * 200 + 3 * 200 * 200 + 200 * cols)
    rates = ", ".join(f"{name} {flops / statistics.median(v) / 1e9:.0f} GFLOP/s" for name, v in samples.items())
    return summary(samples, "oneDNN threads") + f"; {rates}"


def small_forward_part(rounds: int) -> str:
    """Part 5: per (members' hidden sizes, rows) the batched matmuls' time as a multiple of the fused forward's."""
    linear = onednn_fused_linear(th.float32)
    if linear is None:
        return "oneDNN's fused linear is not available in this torch build"
    results = []
    for hidden in ((64,) * 3, (128,) * 3, (200,) * 4):
        th.manual_seed(0)
        model = ProbabilisticEnsemble(18, 6, 5, hidden)
        cells = []
        for rows in (100, 200, 300, 400, 600, 1000):
            x = th.randn(rows, model.in_dim)
            with th.inference_mode():
                alternatives = {
                    "fused": functools.partial(kernels.member_layers, model, x, mean_only=True),
                    "batched": functools.partial(batched_mean, model, x),
                }
                assert th.allclose(alternatives["fused"](), alternatives["batched"](), atol=1e-5)
                samples = interleave(alternatives, rounds, max(2, 4000 // rows))
            ratio = statistics.median(b / a for a, b in zip(samples["fused"], samples["batched"], strict=True))
            cells.append(f"{rows} rows {statistics.median(samples['fused']) * 1e3:.2f} ms / {ratio:.2f}x")
        results.append(f"{len(hidden)} x {hidden[0]}: " + ", ".join(cells))
    return "fused forward time / batched as a multiple of it: " + "; ".join(results)


def batched_mean(model: ProbabilisticEnsemble, x: th.Tensor) -> th.Tensor:
    """The shared-input mean through the batched matmuls whatever the size (``kernels.shared_input_mean``'s other path)."""
    saved = kernels.FUSED_MIN_ROWS
    kernels.FUSED_MIN_ROWS = x.shape[0] + 1
    try:
        return kernels.shared_input_mean(model, x)
    finally:
        kernels.FUSED_MIN_ROWS = saved


def elite_part(rounds: int) -> str:
    dim, k = 30 * 774, 50
    generator = th.Generator().manual_seed(0)
    elites = th.randn(1, k, dim, generator=generator)
    valid = th.ones(1, k, dtype=th.bool)
    valid[0, -3:] = False  # a few non-finite returns

    def elementwise() -> tuple[th.Tensor, th.Tensor]:
        weight = valid.unsqueeze(-1).to(elites.dtype)
        count = weight.sum(dim=1).clamp(min=1.0)
        mean = (elites * weight).sum(dim=1) / count
        return mean, ((elites - mean.unsqueeze(1)) ** 2 * weight).sum(dim=1) / count

    deviation = th.empty_like(elites)

    def products() -> tuple[th.Tensor, th.Tensor]:
        weight = (valid / valid.sum(dim=1, keepdim=True).clamp(min=1)).to(elites.dtype).unsqueeze(1)
        mean = th.bmm(weight, elites)
        th.sub(elites, mean, out=deviation).square_()
        return mean.squeeze(1), th.bmm(weight, deviation).squeeze(1)

    for a, b in zip(elementwise(), products(), strict=True):
        assert th.allclose(a, b, atol=1e-5)
    return summary(interleave({"element-wise": elementwise, "products": products}, rounds, 10), "element-wise")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--rounds", type=int, default=15)
    parser.add_argument("--parts", type=int, nargs="+", choices=range(1, 6), default=list(range(1, 6)))
    args = parser.parse_args()
    th.set_num_threads(args.threads)
    command = "python " + " ".join(sys.argv)
    machine = describe_machine(args.threads)
    rounds, threads = args.rounds, args.threads
    all_parts: dict[int, list[tuple[str, Callable[[], str]]]] = {
        1: [("CEM sampling, one POPLIN-P Sep iteration (11.6 M samples)", lambda: sampling_part(rounds))],
        2: [("one 500 x 200 x 200 layer, oneDNN linear", lambda: layer_part(rounds))],
        3: [
            ("one expectation forward, 5 x 4 x 200 on 500 rows", lambda: forward_part(rounds, threads)),
            ("one expectation forward, 5 x 4 x 200 on 1000 rows (two envs)", lambda: forward_part(rounds, threads, 1000)),
        ],
        4: [("CEM elite statistics, one POPLIN-P Sep iteration (50 x 23,220)", lambda: elite_part(rounds))],
        5: [("one expectation forward at CPU-budget sizes, fused vs batched", lambda: small_forward_part(rounds))],
    }
    parts = [(name, run()) for number in sorted(set(args.parts)) for name, run in all_parts[number]]
    peak_note = f"(sgemm 2048^3 right after: {2 * 2048**3 / min(timed_matmul() for _ in range(5)) / 1e9:.0f} GFLOP/s)"
    for part, result in parts:
        print(f"{part}: {result}")
        append_row(
            "Planner parts (`benchmarks/planner_parts.py`)",
            "Alternatives interleaved in one process; medians per call and median per-round ratios.",
            ["date", "command", "part", "result", "machine"],
            [str(datetime.date.today()), f"`{command}`", part, f"{result} {peak_note}", machine],
        )


def timed_matmul(size: int = 2048) -> float:
    a = th.randn(size, size)
    a @ a
    start = time.perf_counter()
    a @ a
    return time.perf_counter() - start


if __name__ == "__main__":
    main()
