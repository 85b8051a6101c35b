"""
The return of a uniform random policy on each of the POPLIN paper's 13 tasks (``sb3_poplin.tasks.paper_suite``).

Episode ``i`` (0-based) resets the env with seed ``seed + i`` and draws its actions from a sampler seeded with
``seed + i``; every episode runs until the env's time limit (none of these tasks terminates early). Prints a
Markdown table: paper name, env id, steps per episode, the action range drawn from, mean ± std of the return over
the episodes::

    python benchmarks/diagnosis/paper_random_returns.py --episodes 20 --seed 0

Action range. By default the actions are uniform over the env's action space, its full range (±20 on Reacher3D, ±2
on Pusher, ±3 on InvertedPendulum, ±1 elsewhere). ``--unit-range`` draws them uniformly in [-1, 1] per dimension
whatever the env's bounds and sends them unscaled, as the original code sends its actions (clipped to the bounds
only where a bound lies inside ±1, as MuJoCo's control range would clamp them; on these 13 tasks none does). Where
the two differ: the original's policy networks clip their output to ±1 in env units whatever the env's bounds
(the reference ``poplin_original.md``, quirk Q5), while its random warm-up episode draws over the full
range [lb, ub]; the paper's "Random" row on Reacher3D and Pusher lies near the [-1, 1] returns, far from the full
range's (``benchmarks/RESULTS.md``). On the tasks whose range is ±1 both options draw the same actions. Both draw
from the same seeded uniforms (``Box.sample`` scales one uniform per dimension into the bounds), so their action
sequences are the same numbers rescaled::

    python benchmarks/diagnosis/paper_random_returns.py --episodes 20 --seed 0 --unit-range \
        --tasks Reacher3D Pusher InvertedPendulum
"""

from __future__ import annotations

import argparse
import sys

import gymnasium as gym
import numpy as np
from gymnasium import spaces

import sb3_poplin  # noqa: F401  (registers the sb3_poplin/... envs)
from sb3_poplin.tasks import make_task
from sb3_poplin.tasks.paper_suite import PAPER_TASKS


def action_sampler(action_space: spaces.Box, unit_range: bool) -> spaces.Box:
    """
    :param action_space: the env's (bounded) action space
    :param unit_range: draw in [-1, 1] per dimension instead of the env's bounds
    :return: the space the random actions are drawn from
    """
    if not unit_range:
        return action_space
    return spaces.Box(-1.0, 1.0, shape=action_space.shape, dtype=action_space.dtype)  # type: ignore[arg-type]


def range_label(action_space: spaces.Box, unit_range: bool) -> str:
    """:return: the range the actions were drawn from, as the RESULTS rows state it"""
    bound = float(np.max(np.abs(np.concatenate([action_space.low, action_space.high]))))
    symmetric = np.allclose(-action_space.low, action_space.high) and np.allclose(action_space.high, bound)
    env_range = f"±{bound:g}" if symmetric else f"[{action_space.low.tolist()}, {action_space.high.tolist()}]"
    if unit_range:
        return "[-1, 1]" + (" (the env's full range)" if env_range == "±1" else f" (env {env_range})")
    return f"{env_range} (the env's full range)"


def random_returns(env_id: str, episodes: int, seed: int, unit_range: bool = False) -> tuple[np.ndarray, int, str]:
    """
    :param env_id: gymnasium id (made with its task's ``env_kwargs``)
    :param episodes: episodes to run
    :param seed: seed of the first episode
    :param unit_range: actions uniform in [-1, 1] (clipped to the env's bounds) instead of over the env's bounds
    :return: the episodes' returns, the steps of the last one and the action range drawn from
    """
    env = gym.make(env_id, **make_task(env_id).env_kwargs)
    action_space = env.action_space
    assert isinstance(action_space, spaces.Box)
    sampler = action_sampler(action_space, unit_range)
    returns = []
    steps = 0
    for episode in range(episodes):
        env.reset(seed=seed + episode)
        sampler.seed(seed + episode)
        total, steps, done = 0.0, 0, False
        while not done:
            action = np.clip(sampler.sample(), action_space.low, action_space.high)
            _, reward, terminated, truncated, _ = env.step(action)
            total += float(reward)
            steps += 1
            done = terminated or truncated
        returns.append(total)
    env.close()
    return np.asarray(returns), steps, range_label(action_space, unit_range)


def main(argv: list[str] | None = None) -> int:
    """
    :param argv: the arguments (``None``: ``sys.argv[1:]``)
    :return: the exit code
    """
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--episodes", type=int, default=20, help="episodes per task (default 20)")
    parser.add_argument("--seed", type=int, default=0, help="seed of the first episode (default 0)")
    parser.add_argument(
        "--unit-range",
        action="store_true",
        help="actions uniform in [-1, 1] per dimension, sent unscaled (default: uniform over the env's action space)",
    )
    parser.add_argument(
        "--tasks", nargs="+", choices=list(PAPER_TASKS), metavar="NAME", help="paper task names (default: all 13)"
    )
    options = parser.parse_args(argv)
    if options.episodes < 2:
        parser.error("--episodes must be >= 2 (the table gives a standard deviation)")
    print("| paper task | env id | steps | actions drawn | random policy return (mean ± std) |")
    print("|---|---|---|---|---|")
    for name, task in PAPER_TASKS.items():
        if options.tasks and name not in options.tasks:
            continue
        returns, steps, drawn = random_returns(task.env_id, options.episodes, options.seed, options.unit_range)
        print(f"| {name} | `{task.env_id}` | {steps} | {drawn} | {returns.mean():.1f} ± {returns.std():.1f} |", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
