"""
POPLIN-P's per-candidate policy products, three ways (issue 33): every candidate runs its own perturbed network
``x (theta + omega_r)``; the shared part is one ``addmm``, the per-candidate part ``x_r omega_r`` is a batch of
1 x in x out products. Timed at the paper's sizes (500 candidates, horizon 30, policy 17 -> 32 -> 6 as in
``plan_time_variants.py --setting paper``, W = 774) with the perturbations read in place from the candidates'
buffer, as ``PolicyNetwork.forward_perturbed`` reads them:

- ``bmm``: ``baddbmm`` (what the package does),
- ``mulsum``: an element-wise product and a sum over the input axis,
- ``einsum``: ``torch.einsum("ri,rio->ro")``.

    python benchmarks/speed/perturbed_matvec.py [--threads 1] [--rounds 7]

Prints the largest difference to ``bmm`` and the median time per imagined step of each, interleaved rounds.
"""

from __future__ import annotations

import argparse
import time

import torch as th

CANDIDATES, HORIZON, SHAPES = 500, 30, ((17, 32), (32, 6))


def forward(z: th.Tensor, x0: th.Tensor, params: list[tuple[th.Tensor, th.Tensor]], t: int, mode: str) -> th.Tensor:
    """The perturbed policy of step ``t`` for every candidate, ``[R, out]``."""
    width = sum(i * o + o for i, o in SHAPES)
    noise = z[:, t * width : (t + 1) * width]
    x, offset = x0, 0
    for k, ((d_in, d_out), (weight, bias)) in enumerate(zip(SHAPES, params, strict=True)):
        d_weight = noise[:, offset : offset + d_in * d_out].view(-1, d_in, d_out)
        offset += d_in * d_out
        d_bias = noise[:, offset : offset + d_out]
        offset += d_out
        shared = th.addmm(bias, x, weight).add_(d_bias)
        if mode == "bmm":
            x = th.baddbmm(shared.unsqueeze(1), x.unsqueeze(1), d_weight).squeeze(1)
        elif mode == "mulsum":
            x = (d_weight * x.unsqueeze(2)).sum(1).add_(shared)
        else:
            x = th.einsum("ri,rio->ro", x, d_weight).add_(shared)
        if k < len(SHAPES) - 1:
            x = th.tanh(x)
    return x


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--rounds", type=int, default=7)
    args = parser.parse_args()
    th.set_num_threads(args.threads)
    th.manual_seed(0)
    width = sum(i * o + o for i, o in SHAPES)
    z = th.randn(CANDIDATES, HORIZON * width)
    x0 = th.randn(CANDIDATES, SHAPES[0][0])
    params = [(th.randn(i, o), th.randn(o)) for i, o in SHAPES]
    modes = ("bmm", "mulsum", "einsum")
    reference = forward(z, x0, params, 3, "bmm")
    for mode in modes[1:]:
        print(f"{mode}: largest difference to bmm {(forward(z, x0, params, 3, mode) - reference).abs().max().item():.1e}")
    times: dict[str, list[float]] = {mode: [] for mode in modes}
    for _ in range(args.rounds):
        for mode in modes:
            start = time.perf_counter()
            for _ in range(5):
                for t in range(HORIZON):
                    forward(z, x0, params, t, mode)
            times[mode].append((time.perf_counter() - start) / (5 * HORIZON) * 1e3)
    for mode, values in times.items():
        values.sort()
        print(f"{mode:8s} {values[len(values) // 2]:.3f} ms per step (fastest round {values[0]:.3f})")


if __name__ == "__main__":
    main()
