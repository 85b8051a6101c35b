"""
``make demo``: train a small model-based agent on a CPU, evaluate it next to a random policy, and
write the model, a learning-curve PNG and a JSON summary into an output folder.

    python -m sb3_poplin.demo [--variant pets] [--env Pendulum-v1] [--steps 3000] [--out demo_output]
"""

from __future__ import annotations

import argparse
import json
import os
import time

import gymnasium as gym
import numpy as np
import torch as th
from stable_baselines3.common.callbacks import BaseCallback
from stable_baselines3.common.evaluation import evaluate_policy

from sb3_poplin import POPLIN

# Planner and model sized for 2 CPU cores (the paper's 500 x 30 x 5 planner is for GPUs).
CPU_SETTINGS: dict = dict(
    horizon=25,
    population_size=200,
    num_elites=20,
    cem_iterations=3,
    ensemble_size=5,
    dynamics_net_arch=(64, 64, 64),
)


class EpisodeRecorder(BaseCallback):
    """Records (env steps, return) of every finished training episode."""

    def __init__(self) -> None:
        super().__init__()
        self.steps: list[int] = []
        self.returns: list[float] = []

    def _on_step(self) -> bool:
        for info in self.locals.get("infos", []):
            if "episode" in info:
                self.steps.append(self.num_timesteps)
                self.returns.append(float(info["episode"]["r"]))
        return True


def random_policy_returns(env_id: str, episodes: int, seed: int) -> list[float]:
    """Returns of uniform random actions, for reference."""
    env = gym.make(env_id)
    env.action_space.seed(seed)
    returns = []
    for episode in range(episodes):
        env.reset(seed=seed + episode)
        total, done = 0.0, False
        while not done:
            _, reward, terminated, truncated, _ = env.step(env.action_space.sample())
            total += float(reward)
            done = terminated or truncated
        returns.append(total)
    return returns


def plot_curve(
    path: str, env_id: str, variant: str, recorder: EpisodeRecorder, final: tuple[float, float], random: float
) -> bool:
    """Write the learning curve; returns False when matplotlib is not installed."""
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        return False
    fig, ax = plt.subplots(figsize=(6, 4))
    ax.plot(recorder.steps, recorder.returns, "o-", label=f"{variant} training episodes")
    ax.axhline(random, color="grey", linestyle="--", label=f"random policy ({random:.0f})")
    ax.errorbar(
        [recorder.steps[-1] if recorder.steps else 0],
        [final[0]],
        yerr=[final[1]],
        fmt="s",
        color="C3",
        capsize=4,
        label=f"final evaluation ({final[0]:.0f} ± {final[1]:.0f})",
    )
    ax.set_xlabel("environment steps")
    ax.set_ylabel("episode return")
    ax.set_title(f"sb3_poplin {variant} on {env_id}")
    ax.legend(loc="best")
    ax.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)
    return True


def main(argv: list[str] | None = None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--variant", default="pets", help="pets | rs")
    parser.add_argument("--env", default="Pendulum-v1")
    parser.add_argument("--steps", type=int, default=3000)
    parser.add_argument("--eval-episodes", type=int, default=10)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--threads", type=int, default=1, help="torch threads (1 is fastest on small CPUs)")
    parser.add_argument("--out", default="demo_output")
    args = parser.parse_args(argv)

    th.set_num_threads(args.threads)
    os.makedirs(args.out, exist_ok=True)
    print(f"Training {args.variant} on {args.env} for {args.steps} steps with CPU settings {CPU_SETTINGS}", flush=True)
    model = POPLIN(args.variant, args.env, seed=args.seed, verbose=0, **CPU_SETTINGS)
    recorder = EpisodeRecorder()
    start = time.time()
    model.learn(args.steps, callback=recorder, progress_bar=False)
    train_time = time.time() - start
    for steps, ret in zip(recorder.steps, recorder.returns, strict=True):
        print(f"  episode ending at step {steps:6d}: return {ret:9.1f}", flush=True)

    start = time.time()
    env = model.get_env()
    assert env is not None
    returns, _ = evaluate_policy(model, env, n_eval_episodes=args.eval_episodes, return_episode_rewards=True)
    assert isinstance(returns, list)
    eval_time = time.time() - start
    random = random_policy_returns(args.env, args.eval_episodes, seed=args.seed + 1000)
    mean, std = float(np.mean(returns)), float(np.std(returns))

    model_path = os.path.join(args.out, f"{args.variant}_{args.env}.zip")
    model.save(model_path)
    plot_path = os.path.join(args.out, "learning_curve.png")
    plotted = plot_curve(plot_path, args.env, args.variant, recorder, (mean, std), float(np.mean(random)))
    summary = dict(
        variant=args.variant,
        env=args.env,
        steps=args.steps,
        settings=CPU_SETTINGS,
        eval_returns=[float(r) for r in returns],
        eval_mean=mean,
        eval_std=std,
        random_mean=float(np.mean(random)),
        random_std=float(np.std(random)),
        train_seconds=round(train_time, 1),
        eval_seconds=round(eval_time, 1),
    )
    with open(os.path.join(args.out, "summary.json"), "w") as file:
        json.dump(summary, file, indent=2)

    print()
    print(
        f"{args.variant} on {args.env} after {args.steps} steps",
        f"({train_time:.0f} s training, {eval_time:.0f} s evaluation):",
    )
    print(f"  {args.variant:>8}: {mean:8.1f} ± {std:6.1f}  over {args.eval_episodes} episodes")
    print(f"  {'random':>8}: {np.mean(random):8.1f} ± {np.std(random):6.1f}")
    print(f"Wrote {model_path}, {os.path.join(args.out, 'summary.json')}" + (f" and {plot_path}" if plotted else ""))
    return summary


if __name__ == "__main__":
    main()
