"""
Every POPLIN configuration on Pendulum-v1 with the CPU planner settings: MPC and policy-control
returns after a fixed number of env steps, and wall time. Adds one row per configuration to
benchmarks/RESULTS.md.

    python benchmarks/probes/pendulum_variants.py [--configs poplin-a/init poplin-p/sep/avg ...] [--steps 3000]
"""

from __future__ import annotations

import argparse
import datetime
import os
import sys
import time

import numpy as np
import torch as th
from stable_baselines3.common.evaluation import evaluate_policy

from sb3_poplin import POPLIN
from sb3_poplin.experiments.presets import poplin_settings
from sb3_poplin.variants import NAMED_CONFIGURATIONS, configuration

# benchmarks/, where results_file.py (shared by the scripts of every subfolder) lives
sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
from results_file import append_row, describe_machine

DEFAULT_CONFIGS = ["pets", "poplin-a/init", "poplin-a/replan", "poplin-p/sep/avg", "poplin-p/sep/bc", "poplin-p/sep/gan"]
DEFAULT_CONFIGS += ["poplin-p/uni/avg"]
# the CPU planner settings of Pendulum-v1 (poplin_cpu.yml), the configuration's variant and options
CPU_SETTINGS = {key: value for key, value in poplin_settings("Pendulum-v1").items() if key not in ("policy", "noise")}


def run(name: str, steps: int, seed: int, episodes: int) -> dict:
    model = POPLIN(env="Pendulum-v1", seed=seed, **{**CPU_SETTINGS, **configuration(name)})
    start = time.time()
    model.learn(steps)
    train_time = time.time() - start
    env = model.get_env()
    assert env is not None
    start = time.time()
    mpc, _ = evaluate_policy(model, env, n_eval_episodes=episodes, return_episode_rewards=True)
    eval_time = time.time() - start
    policy = None
    if model.variant.startswith("poplin"):
        model.control = "policy"
        policy, _ = evaluate_policy(model, env, n_eval_episodes=episodes, return_episode_rewards=True)
    return dict(name=name, mpc=mpc, policy=policy, train_time=train_time, eval_time=eval_time)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--configs", nargs="+", default=DEFAULT_CONFIGS, choices=list(NAMED_CONFIGURATIONS))
    parser.add_argument("--steps", type=int, default=3000)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--episodes", type=int, default=10)
    args = parser.parse_args()
    th.set_num_threads(1)
    command = "python " + " ".join(sys.argv)
    machine = describe_machine(1)
    settings = ", ".join(f"{k}={v}" for k, v in CPU_SETTINGS.items())
    for name in args.configs:
        r = run(name, args.steps, args.seed, args.episodes)

        def fmt(returns: list[float] | None) -> str:
            return "n/a" if returns is None else f"{np.mean(returns):.1f} ± {np.std(returns):.1f}"

        cells = [
            str(datetime.date.today()),
            f"`{command}`",
            name,
            f"seed {args.seed}, {args.steps} steps, {settings}",
            fmt(r["mpc"]),
            fmt(r["policy"]),
            f"{r['train_time']:.0f} s + {r['eval_time']:.0f} s",
            machine,
        ]
        print(" | ".join(cells), flush=True)
        append_row(
            "Pendulum-v1: every configuration at 3000 env steps (`benchmarks/pendulum_variants.py`)",
            "MPC = planning with the learned model; policy = the distilled network alone. Random actions score about -1250.",
            ["date", "command", "configuration", "setting", "MPC return", "policy return", "train + MPC eval time", "machine"],
            cells,
        )


if __name__ == "__main__":
    main()
