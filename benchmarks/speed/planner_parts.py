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
5. The expectation forward (5 members of 3 x 64, 3 x 128 and 4 x 200, 100-2000 rows): the three forward paths of
   ``sb3_poplin.kernels`` (batched matmuls, transposed per-member products, fused per-member oneDNN layers), the
   times behind the per-host choice from ``kernels.PROBE_MIN_ROWS`` rows on.
6. Where a whole plan's time goes, as fractions of the plan (PETS expectation and TS1-20, POPLIN-P Sep, at the paper
   setting and at ``poplin_cpu.yml``'s planner for PETSCheetah): the parts are timed by wrapping the planner's own
   functions (candidate sampling, the search space's actions, the ensemble's no-gradient forward, the task's reward;
   the rest of the model step is the propagation minus the forward, CEM's own work the plan minus the rollout and the
   sampling, the forward's products and biases the forward minus its SiLU calls; the fused oneDNN path, where a host
   takes it, has its SiLU inside the products).

    python benchmarks/speed/planner_parts.py --threads 1 --parts 6

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
    """Part 5: per (members' hidden sizes, rows) each forward path's time as a multiple of the batched path's."""
    paths = [p for p in kernels.PATHS if p != "fused" or onednn_fused_linear(th.float32) is not None]
    results = []
    for hidden in ((64,) * 3, (128,) * 3, (200,) * 4):
        th.manual_seed(0)
        model = ProbabilisticEnsemble(18, 6, 5, hidden)
        cells = []
        for rows in (100, 200, 300, 400, 600, 1000, 2000):
            x = th.randn(rows, model.in_dim)
            with th.inference_mode():
                alternatives = {path: functools.partial(kernels.LAYERS[path], model, x, True) for path in paths}
                for path in paths:
                    assert th.allclose(alternatives[path](), alternatives["batched"](), atol=1e-5)
                samples = interleave(alternatives, rounds, max(2, 4000 // rows))
            base = samples["batched"]
            medians = [statistics.median(a / b for a, b in zip(samples[p], base, strict=True)) for p in paths[1:]]
            ratios = " / ".join(f"{m:.2f}x" for m in medians)
            cells.append(f"{rows} rows {statistics.median(samples['batched']) * 1e3:.2f} ms, {ratios}")
        results.append(f"{len(hidden)} x {hidden[0]}: " + "; ".join(cells))
    return f"batched forward time, then {' / '.join(paths[1:])} as multiples of it: " + " | ".join(results)


class PartTimer:
    """Wall time spent in wrapped functions, by label (the outermost call of a label counts; no nesting per label)."""

    def __init__(self) -> None:
        self.seconds: dict[str, float] = {}
        self.depth: dict[str, int] = {}

    def wrap(self, owner: object, name: str, label: str) -> None:
        original = getattr(owner, name)

        @functools.wraps(original)
        def timed(*args: object, **kwargs: object) -> object:
            self.depth[label] = self.depth.get(label, 0) + 1
            start = time.perf_counter()
            try:
                return original(*args, **kwargs)
            finally:
                self.depth[label] -= 1
                if self.depth[label] == 0:
                    self.seconds[label] = self.seconds.get(label, 0.0) + time.perf_counter() - start

        setattr(owner, name, timed)


PLAN_SETTINGS = {
    "paper": ("HalfCheetah-v5", dict(horizon=30, population_size=500, num_elites=50, cem_iterations=5, ensemble_size=5)),
    "cpu": ("sb3_poplin/PETSCheetah-v0", {}),
}
PLAN_VARIANTS = {
    "PETS": dict(policy="pets"),
    "PETS TS1-20": dict(policy="pets", propagation="ts1", num_particles=20),
    "POPLIN-P Sep": dict(policy="poplin-p", noise="sep"),
}


def plan_breakdown_part(rounds: int) -> str:
    """Part 6: fractions of a plan's wall time per part, per setting and variant (the median plan of ``rounds``)."""
    import warnings

    import torch.nn.functional as F

    from sb3_poplin import POPLIN, planning, sampling
    from sb3_poplin.dynamics import ProbabilisticEnsemble as Ensemble
    from sb3_poplin.experiments.presets import poplin_settings

    cells = []
    for setting, (env_id, planner) in PLAN_SETTINGS.items():
        for name, variant in PLAN_VARIANTS.items():
            settings = dict(planner) if planner else poplin_settings(env_id)  # the CPU preset's planner and model
            settings = {k: v for k, v in settings.items() if k not in ("policy", "noise")}
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                model = POPLIN(env=env_id, seed=0, **{**settings, **variant})
            timer = PartTimer()
            model.planner.reward_fn = _timed(timer, model.planner.reward_fn, "reward")
            wrapped = {
                (sampling.CandidateSampler, "sample"): "sampling",
                (type(model.planner.search_space), "actions"): "search space actions",
                (Ensemble, "propagate"): "model step",
                (planning.MPCPlanner, "rollout"): "rollout",
                (planning.MPCPlanner, "plan"): "plan",
                (kernels, "shared_input_mean"): "forward",
                (kernels, "no_grad_output"): "forward",
                (F, "silu"): "SiLU",  # only the ensemble's hidden layers call it while planning
            }
            saved = {key: getattr(*key) for key in wrapped}
            try:
                for (owner, attr), label in wrapped.items():
                    timer.wrap(owner, attr, label)
                obs = model.observation_space.sample()
                for _ in range(2):
                    model.predict(obs)
                plans = []
                for _ in range(rounds):
                    timer.seconds.clear()
                    model.predict(obs)
                    plans.append(dict(timer.seconds))
            finally:
                for (owner, attr), original in saved.items():
                    setattr(owner, attr, original)
            t = sorted(plans, key=lambda p: p["plan"])[len(plans) // 2]
            get = functools.partial(lambda key, t: t.get(key, 0.0), t=t)
            parts = {
                "network products and biases": get("forward") - get("SiLU"),
                "SiLU": get("SiLU"),
                "model step outside the forward": get("model step") - get("forward"),
                "search space actions": get("search space actions"),
                "reward": get("reward"),
                "rollout loop": get("rollout") - get("model step") - get("search space actions") - get("reward"),
                "sampling": get("sampling"),
                "CEM and the rest": get("plan") - get("rollout") - get("sampling"),
            }
            total = get("plan")
            shares = ", ".join(f"{k} {v / total:.0%}" for k, v in parts.items() if abs(v) / total >= 0.005)
            cells.append(f"{setting} {name}: {total * 1e3:.0f} ms = {shares}")
    return " | ".join(cells)


def _timed(timer: PartTimer, fn: Callable[..., th.Tensor] | None, label: str) -> Callable[..., th.Tensor] | None:
    if fn is None:
        return None

    class Holder:
        call = staticmethod(fn)

    timer.wrap(Holder, "call", label)
    return Holder.call


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
    parser.add_argument("--parts", type=int, nargs="+", choices=range(1, 7), default=list(range(1, 7)))
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
        5: [("one expectation forward, the three paths at 100-2000 rows", lambda: small_forward_part(rounds))],
        6: [("where a plan's time goes (fractions of the median plan)", lambda: plan_breakdown_part(rounds))],
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
