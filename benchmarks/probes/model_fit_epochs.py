"""
How many epochs per model fit does a MuJoCo task need? Fits the dynamics ensemble on a few episodes of
exploratory data (uniform and smoothed random actions) with several epoch counts and reports the open-loop
prediction error on a held-out episode, in units of each state dimension's standard deviation.

    python benchmarks/probes/model_fit_epochs.py [--env HalfCheetah-v5] [--epochs 5 25 60]

Adds one row to benchmarks/RESULTS.md (section "Model fit epochs").
"""

from __future__ import annotations

import argparse
import datetime
import os
import sys
import time

import gymnasium as gym
import numpy as np
import torch as th

from sb3_poplin import POPLIN
from sb3_poplin.tasks import make_env

# benchmarks/, where results_file.py (shared by the scripts of every subfolder) lives
sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
from results_file import append_row, describe_machine


def episode(env: gym.Env, rng: np.random.Generator, seed: int, smooth: float) -> tuple[np.ndarray, np.ndarray]:
    """:return: observations ``[T + 1, o]`` and actions ``[T, a]`` (scaled = env units for [-1, 1] bounds)"""
    obs, _ = env.reset(seed=seed)
    observations, actions = [obs], []
    action = np.zeros(env.action_space.shape)
    while True:
        fresh = rng.uniform(-1.0, 1.0, env.action_space.shape)
        action = smooth * action + (1.0 - smooth) * fresh
        obs, _, terminated, truncated, _ = env.step(action)
        observations.append(obs)
        actions.append(action)
        if terminated or truncated:
            return np.array(observations, np.float32), np.array(actions, np.float32)


@th.no_grad()
def open_loop_rmse(model: POPLIN, obs: th.Tensor, actions: th.Tensor, horizon: int) -> list[float]:
    """:return: normalised state RMSE after k = 1..horizon open-loop steps from every 5th state"""
    std = obs.std(dim=0).clamp(min=1e-6)
    starts = th.arange(0, len(actions) - horizon + 1, 5)
    states = obs[starts].unsqueeze(1)
    errors = []
    for k in range(horizon):
        states, _ = model.policy.dynamics.propagate(states, actions[starts + k].unsqueeze(1), "expectation")
        errors.append(float((((states[:, 0] - obs[starts + k + 1]) / std) ** 2).mean().sqrt()))
    return errors


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--env", default="HalfCheetah-v5")
    parser.add_argument("--epochs", nargs="+", type=int, default=[5, 25, 60])
    parser.add_argument("--episodes", type=int, default=4, help="training episodes (even: uniform, odd: smoothed)")
    parser.add_argument("--horizon", type=int, default=15)
    parser.add_argument("--arch", nargs="+", type=int, default=[128, 128, 128])
    args = parser.parse_args()
    th.set_num_threads(1)
    env = make_env(args.env)
    assert np.allclose(env.action_space.low, -1) and np.allclose(env.action_space.high, 1), "needs [-1, 1] actions"
    rng = np.random.default_rng(0)
    train = [episode(env, rng, seed, 0.8 if seed % 2 else 0.0) for seed in range(args.episodes)]
    test_obs, test_actions = (th.as_tensor(x) for x in episode(env, rng, 99, 0.8))
    obs = th.as_tensor(np.concatenate([o[:-1] for o, _ in train]))
    next_obs = th.as_tensor(np.concatenate([o[1:] for o, _ in train]))
    actions = th.as_tensor(np.concatenate([a for _, a in train]))
    cells = []
    for epochs in args.epochs:
        model = POPLIN("pets", env, dynamics_net_arch=args.arch, seed=0, model_epochs=epochs)
        start = time.perf_counter()
        model.policy.dynamics.fit(
            obs, actions, next_obs, model.policy.dynamics_optimizer, epochs=epochs, generator=th.Generator().manual_seed(0)
        )
        seconds = time.perf_counter() - start
        errors = open_loop_rmse(model, test_obs, test_actions, args.horizon)
        cell = f"{epochs}: {errors[0]:.3f} / {errors[4]:.3f} / {errors[-1]:.3f} ({seconds:.0f} s)"
        print(cell, flush=True)
        cells.append(cell)
    row = [
        str(datetime.date.today()),
        f"`python benchmarks/probes/model_fit_epochs.py --env {args.env} --epochs {' '.join(map(str, args.epochs))}`",
        f"{args.env}, {len(obs)} transitions, 5 x {args.arch} ensemble, batch 32",
        "; ".join(cells),
        describe_machine(1),
    ]
    header = ["date", "command", "data and model", "epochs: RMSE k=1 / k=5 / k=H (fit time)", "machine"]
    intro = (
        "Open-loop prediction error of the ensemble on a held-out episode after one fit with each number of epochs "
        "(state RMSE in units of each dimension's standard deviation)."
    )
    append_row("Model fit epochs", intro, header, row)


if __name__ == "__main__":
    main()
