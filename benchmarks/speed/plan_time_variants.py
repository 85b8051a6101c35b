"""
Plan time of POPLIN-A and POPLIN-P against PETS at the same population, horizon and iterations,
measured in one process (median of ``--repeats`` ``predict`` calls after warm-up). Appends one row
per setting to benchmarks/RESULTS.md with the ratios to PETS.

    python benchmarks/speed/plan_time_variants.py [--setting paper|cpu|cheetah-cpu] [--repeats 5] [--threads 1]
        [--forward-path fused|batched|members] [--dtype float32|bfloat16]

``paper``: HalfCheetah-v5 sizes (17-dim obs, 6-dim action), population 500, horizon 30, 5 CEM
iterations, 5 x (200, 200, 200, 200) ensemble, expectation propagation, policies [64, 64] (A) and
[32] (P, W = 774 parameters). ``cpu``: Pendulum-v1 with the demo's CPU settings. ``cheetah-cpu``:
``sb3_poplin/PETSCheetah-v0``'s ``poplin_cpu.yml`` entry (population 200, horizon 15, 3 iterations,
5 x 3 x 128), the planner of the fidelity A/B and of issue 18's comparison. ``--forward-path`` forces the
ensemble's forward path (``SB3_POPLIN_FORWARD_PATH``; default: the one this host chose, see ``sb3_poplin.kernels``).
``--dtype bfloat16`` plans every variant with ``planning_dtype="bfloat16"``; ``--dtype both`` times each variant in
both dtypes, back to back, and gives the fp32 / bf16 ratio per variant.
"""

from __future__ import annotations

import argparse
import datetime
import os
import sys
import warnings

import torch as th

from sb3_poplin import POPLIN, kernels
from sb3_poplin.experiments.presets import poplin_settings
from sb3_poplin.variants import configuration

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))  # speed/: planning_speed
# benchmarks/, where results_file.py (shared by the scripts of every subfolder) lives
sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
from planning_speed import time_plans
from results_file import append_row, describe_machine

SETTINGS = {  # the packaged files' planner settings (poplin.yml / poplin_cpu.yml)
    "paper": ("HalfCheetah-v5", poplin_settings("HalfCheetah-v5", "paper", learned_reward=True, buffer_size=1000)),
    "cpu": ("Pendulum-v1", poplin_settings("Pendulum-v1")),
    "cheetah-cpu": ("sb3_poplin/PETSCheetah-v0", poplin_settings("sb3_poplin/PETSCheetah-v0")),
}
# the distillation does not change the plan: one configuration per search space
VARIANTS = {name: configuration(name) for name in ("pets", "poplin-a/init", "poplin-a/replan")}
VARIANTS.update({"poplin-p/sep": configuration("poplin-p/sep/avg"), "poplin-p/uni": configuration("poplin-p/uni/avg")})


def plan_time(env_id: str, settings: dict, variant: dict, repeats: int) -> float:
    """Median seconds per single-env ``predict`` (an untrained model plans at the same cost)."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        model = POPLIN(env=env_id, seed=0, **{**settings, **variant})
    return time_plans(model, model.observation_space.sample(), repeats)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--setting", choices=list(SETTINGS), default="paper")
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--forward-path", choices=["batched", "members", "fused"], default=None, help="force the forward path")
    parser.add_argument("--dtype", choices=["float32", "bfloat16", "both"], default="float32", help="planning_dtype")
    args = parser.parse_args()
    th.set_num_threads(args.threads)
    if args.forward_path is not None:
        os.environ[kernels.PATH_ENV] = args.forward_path
    env_id, settings = SETTINGS[args.setting]
    dtypes = ["float32", "bfloat16"] if args.dtype == "both" else [args.dtype]
    times: dict[str, dict[str, float]] = {name: {} for name in VARIANTS}
    for name, variant in VARIANTS.items():
        for dtype in dtypes:  # both dtypes of a variant back to back: their ratio is timed under the same load
            times[name][dtype] = plan_time(env_id, {**settings, "planning_dtype": dtype}, variant, args.repeats)
    results = {name: per_dtype[dtypes[-1]] for name, per_dtype in times.items()}
    pets = results["pets"]
    if len(dtypes) == 1:
        cells = ", ".join(f"{name} {t * 1000:.0f} ms ({t / pets:.2f}x)" for name, t in results.items())
    else:
        cells = ", ".join(
            f"{name} fp32 {t['float32'] * 1000:.0f} ms, bf16 {t['bfloat16'] * 1000:.0f} ms "
            f"({t['float32'] / t['bfloat16']:.2f}x)"
            for name, t in times.items()
        )
        for name, t in times.items():
            print(f"{name:16s} fp32 {t['float32'] * 1000:8.1f} ms  bf16 {t['bfloat16'] * 1000:8.1f} ms")
    command = "python " + " ".join(sys.argv)
    machine = describe_machine(args.threads)
    for name, t in results.items():
        print(f"{name:16s} {t * 1000:8.1f} ms  {t / pets:5.2f}x PETS ({dtypes[-1]})")
    append_row(
        "Plan time of the variants against PETS (`benchmarks/plan_time_variants.py`)",
        "Median time of one single-env `predict` (a full plan), all variants in one process run; ratio to PETS in brackets.",
        ["date", "command", "setting", "time per plan (ratio to PETS)", "machine"],
        [
            str(datetime.date.today()),
            f"`{command}`",
            f"{args.setting}: {env_id}" + ("" if args.dtype == "float32" else f", {args.dtype}"),
            cells,
            machine,
        ],
    )


if __name__ == "__main__":
    main()
