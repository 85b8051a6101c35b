"""
The return of a uniform random policy on each of the POPLIN paper's 13 tasks (``sb3_poplin.tasks.paper_suite``).

Episode ``i`` (0-based) resets the env with seed ``seed + i`` and draws its actions from the action space seeded
with ``seed + i``; every episode runs until the env's time limit (none of these tasks terminates early). Prints a
Markdown table: paper name, env id, steps per episode, mean ± std of the return over the episodes::

    python benchmarks/paper_random_returns.py --episodes 20 --seed 0
"""

from __future__ import annotations

import argparse
import sys

import gymnasium as gym
import numpy as np

import sb3_poplin  # noqa: F401  (registers the sb3_poplin/... envs)
from sb3_poplin.tasks import make_task
from sb3_poplin.tasks.paper_suite import PAPER_TASKS


def random_returns(env_id: str, episodes: int, seed: int) -> tuple[np.ndarray, int]:
    """
    :param env_id: gymnasium id (made with its task's ``env_kwargs``)
    :param episodes: episodes to run
    :param seed: seed of the first episode
    :return: the episodes' returns and the steps of the last one
    """
    env = gym.make(env_id, **make_task(env_id).env_kwargs)
    returns = []
    steps = 0
    for episode in range(episodes):
        env.reset(seed=seed + episode)
        env.action_space.seed(seed + episode)
        total, steps, done = 0.0, 0, False
        while not done:
            _, reward, terminated, truncated, _ = env.step(env.action_space.sample())
            total += float(reward)
            steps += 1
            done = terminated or truncated
        returns.append(total)
    env.close()
    return np.asarray(returns), steps


def main(argv: list[str] | None = None) -> int:
    """
    :param argv: the arguments (``None``: ``sys.argv[1:]``)
    :return: the exit code
    """
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--episodes", type=int, default=20, help="episodes per task (default 20)")
    parser.add_argument("--seed", type=int, default=0, help="seed of the first episode (default 0)")
    options = parser.parse_args(argv)
    if options.episodes < 2:
        parser.error("--episodes must be >= 2 (the table gives a standard deviation)")
    print("| paper task | env id | steps | random policy return (mean ± std) |")
    print("|---|---|---|---|")
    for name, task in PAPER_TASKS.items():
        returns, steps = random_returns(task.env_id, options.episodes, options.seed)
        print(f"| {name} | `{task.env_id}` | {steps} | {returns.mean():.1f} ± {returns.std():.1f} |", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
