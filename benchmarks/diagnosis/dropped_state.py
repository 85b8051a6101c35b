"""
What a ``predict`` loop loses when it drops the returned state: the same trained agent and the same env starts, MPC
episodes played twice, once passing the state and ``episode_start`` back (as ``evaluate_policy`` does) and once
calling ``predict(obs)`` alone, so that every step plans from a fresh start instead of the previous step's shifted
solution. Both with ``deterministic=True``; one row per variant in benchmarks/RESULTS.md.

    python benchmarks/diagnosis/dropped_state.py --env Pendulum-v1 --variants pets poplin-p --steps 2000 --episodes 10
"""

from __future__ import annotations

import argparse
import datetime
import os
import sys
import time

import numpy as np
import torch as th
from stable_baselines3.common.env_util import make_vec_env

from sb3_poplin import POPLIN
from sb3_poplin.experiments.presets import poplin_settings

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
from results_file import append_row, describe_machine

SECTION = "A predict loop that drops the returned state"
INTRO = (
    "The same trained agent (the task's `poplin_cpu.yml` settings, seed 0) and the same env starts (seeds 1000 + "
    "episode), MPC with `deterministic=True`: once passing the returned state and `episode_start` back (as "
    "`evaluate_policy`), once calling `predict(obs)` alone (every step plans from a fresh start). Mean ± std over "
    "episodes; the paired difference is per episode."
)
HEADER = [
    "date",
    "machine",
    "task",
    "variant",
    "training steps",
    "episodes",
    "state passed",
    "state dropped",
    "dropped - passed (paired)",
    "command",
]


def play(model: POPLIN, env_id: str, episode: int, keep_state: bool) -> float:
    """One MPC episode from the start seeded ``1000 + episode``: its return."""
    env = make_vec_env(env_id, n_envs=1, seed=1000 + episode)
    obs = env.reset()
    state, start, total, done = None, np.ones(1, dtype=bool), 0.0, False
    while not done:
        if keep_state:
            action, state = model.predict(obs, state=state, episode_start=start, deterministic=True)
        else:
            action, _ = model.predict(obs, deterministic=True)
        obs, reward, dones, _ = env.step(action)
        total += float(reward[0])
        done = bool(dones[0])
        start = dones
    return total


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--env", default="Pendulum-v1")
    parser.add_argument("--variants", nargs="+", default=["pets", "poplin-p"])
    parser.add_argument("--steps", type=int, default=2000, help="training steps")
    parser.add_argument("--episodes", type=int, default=10)
    parser.add_argument("--no-record", action="store_true")
    args = parser.parse_args()
    th.set_num_threads(1)
    command = "python benchmarks/diagnosis/dropped_state.py " + " ".join(sys.argv[1:])
    for variant in args.variants:
        started = time.time()
        model = POPLIN(env=args.env, seed=0, **poplin_settings(args.env, policy=variant, buffer_size=args.steps))
        model.learn(args.steps)
        passed = np.array([play(model, args.env, k, True) for k in range(args.episodes)])
        dropped = np.array([play(model, args.env, k, False) for k in range(args.episodes)])
        diff = dropped - passed
        cells = [f"{passed.mean():.1f} ± {passed.std():.1f}", f"{dropped.mean():.1f} ± {dropped.std():.1f}"]
        cells.append(f"{diff.mean():.1f} (lower on {int((diff < 0).sum())} of {len(diff)})")
        print(f"{variant}: passed {cells[0]}, dropped {cells[1]}, difference {cells[2]} ({time.time() - started:.0f} s)")
        print("  per episode, passed:", np.round(passed, 1).tolist(), "dropped:", np.round(dropped, 1).tolist())
        if not args.no_record:
            row = [datetime.date.today().isoformat(), describe_machine(threads=1), args.env, variant, str(args.steps)]
            row += [str(args.episodes), *cells, f"`{command}`"]
            append_row(SECTION, INTRO, HEADER, row)


if __name__ == "__main__":
    main()
