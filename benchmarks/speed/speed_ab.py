"""
Planner speed of two code versions, A/B: run this script alternately under each version (``PYTHONPATH`` pointing at
the other checkout) and compare the printed fractions of the sgemm peak (PETS and TS1-20) and plan times (PETS,
POPLIN-P Sep, TS1-20). Uses only the public API (``POPLIN``,
``predict``), so it runs on any version; the FLOPs are counted here, not by the package.

    PYTHONPATH=../old python benchmarks/speed/speed_ab.py --label old --threads 1
    python benchmarks/speed/speed_ab.py --label new --threads 1
"""

from __future__ import annotations

import argparse
import itertools
import json
import os
import sys
import warnings

import torch as th

import sb3_poplin
from sb3_poplin import POPLIN

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))  # speed/: planning_speed
from planning_speed import ENV_ID, PAPER, matmul_peak, time_plans

ARCH = (200, 200, 200, 200)


def pets_flops(model: POPLIN) -> float:
    """Expectation propagation, PETS: every candidate through every member (mean half of the output layer)."""
    dynamics = model.policy.dynamics
    widths = [dynamics.in_dim, *ARCH]
    row = sum(2 * a * b for a, b in itertools.pairwise(widths)) + 2 * ARCH[-1] * dynamics.out_dim
    return float(
        model.settings.cem_iterations * model.settings.horizon * model.settings.population_size * dynamics.ensemble_size * row
    )


def ts1_flops(model: POPLIN) -> float:
    """TS1: every particle through one member, mean and log-variance halves of the output layer."""
    dynamics = model.policy.dynamics
    widths = [dynamics.in_dim, *ARCH]
    row = sum(2 * a * b for a, b in itertools.pairwise(widths)) + 2 * ARCH[-1] * 2 * dynamics.out_dim
    settings = model.settings
    return float(settings.cem_iterations * settings.horizon * settings.population_size * settings.num_particles * row)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--label", required=True)
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--repeats", type=int, default=7)
    args = parser.parse_args()
    th.set_num_threads(args.threads)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        pets = POPLIN("pets", ENV_ID, seed=0, dynamics_net_arch=ARCH, **PAPER)
        poplin = POPLIN("poplin-p", ENV_ID, seed=0, noise="sep", dynamics_net_arch=ARCH, **PAPER)
        ts1 = POPLIN("pets", ENV_ID, seed=0, propagation="ts1", num_particles=20, dynamics_net_arch=ARCH, **PAPER)
    obs = pets.observation_space.sample()
    result = {"label": args.label, "code": os.path.dirname(sb3_poplin.__file__), "threads": args.threads}
    peak = matmul_peak(th.float32)
    pets_s = time_plans(pets, obs, args.repeats)
    poplin_s = time_plans(poplin, obs, args.repeats)
    ts1_s = time_plans(ts1, obs, args.repeats)
    peak = max(peak, matmul_peak(th.float32))  # the best of before and after
    flops = pets_flops(pets)
    result.update(
        peak_gflops=round(peak, 1),
        pets_ms=round(pets_s * 1e3, 1),
        pets_fraction_of_peak=round(flops / pets_s / 1e9 / peak, 4),
        poplin_p_sep_ms=round(poplin_s * 1e3, 1),
        poplin_p_over_pets=round(poplin_s / pets_s, 3),
        ts1_20_ms=round(ts1_s * 1e3, 1),
        ts1_fraction_of_peak=round(ts1_flops(ts1) / ts1_s / 1e9 / peak, 4),
    )
    print(json.dumps(result), flush=True)


if __name__ == "__main__":
    main()
