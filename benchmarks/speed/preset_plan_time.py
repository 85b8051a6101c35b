"""
Plan time of a candidate planner preset against ``poplin_cpu.yml``'s for ``sb3_poplin/PETSCheetah-v0`` (horizon 15,
population 200, 20 elites, 3 CEM iterations), measured in one process: the median of ``--repeats`` single-env
``predict`` calls after warm-up, twice each, interleaved, the lower one kept; for PETS and POPLIN-P Sep (an untrained
model plans at the same cost). Appends one row per variant to benchmarks/RESULTS.md with the ratio new / old.

    python benchmarks/speed/preset_plan_time.py --new horizon=30 population_size=100 num_elites=10 cem_iterations=3 \\
        optimizer=icem "optimizer_kwargs={'noise_beta': 0.25}" [--repeats 7] [--threads 1]
"""

from __future__ import annotations

import argparse
import ast
import datetime
import os
import sys
import warnings
from typing import Any

import torch as th

from sb3_poplin import POPLIN
from sb3_poplin.experiments.presets import poplin_settings

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))  # speed/: planning_speed
# benchmarks/, where results_file.py (shared by the scripts of every subfolder) lives
sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
from planning_speed import time_plans
from results_file import append_row, describe_machine

ENV_ID = "sb3_poplin/PETSCheetah-v0"


def parse(items: list[str]) -> dict[str, Any]:
    """``key=value`` items (values as Python literals, or plain strings) -> keyword arguments."""
    out: dict[str, Any] = {}
    for item in items:
        key, value = item.split("=", 1)
        try:
            out[key] = ast.literal_eval(value)
        except (ValueError, SyntaxError):
            out[key] = value
    return out


def plan_time(policy: str, overrides: dict[str, Any], repeats: int) -> tuple[float, POPLIN]:
    """Median seconds per single-env ``predict`` of a new agent with the packaged entry and ``overrides``."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        model = POPLIN(env=ENV_ID, seed=0, device="cpu", **poplin_settings(ENV_ID, policy=policy, **overrides))
    return time_plans(model, model.observation_space.sample(), repeats), model


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--new", nargs="+", required=True, help="POPLIN keyword arguments over the packaged entry")
    parser.add_argument("--repeats", type=int, default=7)
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--no-record", action="store_true")
    args = parser.parse_args()
    th.set_num_threads(args.threads)
    new = parse(args.new)
    for policy in ("pets", "poplin-p"):
        old_times, new_times = [], []
        for _ in range(2):
            old_time, old_model = plan_time(policy, {}, args.repeats)
            new_time, new_model = plan_time(policy, new, args.repeats)
            old_times.append(old_time)
            new_times.append(new_time)
        old_s, new_s = min(old_times), min(new_times)
        counts = (old_model.planner.optimizer.evaluations(True), new_model.planner.optimizer.evaluations(True))
        print(
            f"{policy}: old {old_s * 1e3:.1f} ms ({counts[0]} candidates), new {new_s * 1e3:.1f} ms "
            f"({counts[1]} candidates): new / old {new_s / old_s:.2f}"
        )
        if args.no_record:
            continue
        row = [
            str(datetime.date.today()),
            describe_machine(args.threads),
            policy,
            f"{old_s * 1e3:.1f} ms ({counts[0]} candidates of H {old_model.settings.horizon})",
            f"{new_s * 1e3:.1f} ms ({counts[1]} candidates of H {new_model.settings.horizon})",
            f"{new_s / old_s:.2f}",
            f"`python benchmarks/speed/preset_plan_time.py --new {' '.join(args.new)} --repeats {args.repeats}`",
        ]
        header = ["date", "machine", "variant", "poplin_cpu.yml's preset", "new preset", "new / old", "command"]
        intro = (
            "Plan time of a candidate CPU preset against `poplin_cpu.yml`'s for sb3_poplin/PETSCheetah-v0 "
            "(`benchmarks/speed/preset_plan_time.py`, issue 35): one process, the lower of two interleaved medians each."
        )
        append_row("Planner presets: plan time against poplin_cpu.yml's", intro, header, row)


if __name__ == "__main__":
    main()
