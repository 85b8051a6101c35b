"""
Does PETS's half-cheetah model preprocessing (``obs_preproc`` / ``targ_proc`` / ``obs_postproc``) make the learned
model of ``sb3_poplin/PETSCheetah-v0`` better? The same ensemble fitted on the same random-action episodes with the
task's hooks and without (raw observations in, deltas out: sb3_poplin 0.2.0), then the open-loop error on held-out
episodes: from every 10th state, the expectation rollout under the executed actions, k steps ahead, of the forward
velocity obs[0] (what the reward pays) and of the k-step return.

    python benchmarks/cheetah_model_hooks.py [--episodes 5] [--epochs 20] [--seeds 0 1 2]
"""

from __future__ import annotations

import argparse

import numpy as np
import torch as th

from sb3_poplin.dynamics import ProbabilisticEnsemble
from sb3_poplin.tasks import make_env, make_task

TASK = "sb3_poplin/PETSCheetah-v0"
HORIZONS = (1, 5, 10, 20)


def episodes(count: int, seed: int) -> list[tuple[np.ndarray, np.ndarray]]:
    """Random-action episodes: observations ``[T + 1, o]`` and actions ``[T, a]`` (in [-1, 1], the env's bounds)."""
    env = make_env(TASK)
    env.action_space.seed(seed)
    out = []
    for i in range(count):
        obs, _ = env.reset(seed=seed * 100 + i)
        observations, actions = [obs], []
        for _ in range(1000):
            action = env.action_space.sample()
            obs, _, terminated, truncated, _ = env.step(action)
            observations.append(obs)
            actions.append(action)
            if terminated or truncated:
                break
        out.append((np.array(observations, dtype=np.float32), np.array(actions, dtype=np.float32)))
    return out


def fit(data: list[tuple[np.ndarray, np.ndarray]], hooks: bool, epochs: int, seed: int) -> ProbabilisticEnsemble:
    th.manual_seed(seed)
    spec = make_task(TASK)
    extra = {} if not hooks else dict(obs_preproc=spec.obs_preproc, targ_proc=spec.targ_proc, obs_postproc=spec.obs_postproc)
    model = ProbabilisticEnsemble(18, 6, ensemble_size=5, hidden_sizes=(128, 128, 128), **extra)
    obs = th.as_tensor(np.concatenate([o[:-1] for o, _ in data]))
    nxt = th.as_tensor(np.concatenate([o[1:] for o, _ in data]))
    actions = th.as_tensor(np.concatenate([a for _, a in data]))
    model.fit(
        obs,
        actions,
        nxt,
        th.optim.Adam(model.parameters(), lr=1e-3),
        epochs=epochs,
        generator=th.Generator().manual_seed(seed),
    )
    return model


@th.no_grad()
def open_loop_errors(model: ProbabilisticEnsemble, data: list[tuple[np.ndarray, np.ndarray]]) -> dict[str, list[float]]:
    """RMSE of the velocity and of the k-step return, per k in HORIZONS, over starts every 10 steps."""
    reward_fn = make_task(TASK).reward_fn
    velocity = {k: [] for k in HORIZONS}
    returns = {k: [] for k in HORIZONS}
    for obs_np, act_np in data:
        obs, actions = th.as_tensor(obs_np), th.as_tensor(act_np)
        starts = th.arange(0, len(actions) - max(HORIZONS), 10)
        state = obs[starts].unsqueeze(1)  # [S, 1, o]
        predicted_return = th.zeros(len(starts))
        real_return = th.zeros(len(starts))
        for k in range(1, max(HORIZONS) + 1):
            a = actions[starts + k - 1]
            next_state, _ = model.propagate(state, a.unsqueeze(1), "expectation")
            predicted_return += reward_fn(state[:, 0], a, next_state[:, 0])
            real_return += reward_fn(obs[starts + k - 1], a, obs[starts + k])
            state = next_state
            if k in HORIZONS:
                velocity[k].append((state[:, 0, 0] - obs[starts + k, 0]).pow(2))
                returns[k].append((predicted_return - real_return).pow(2))
    return {
        "velocity": [float(th.cat(velocity[k]).mean().sqrt()) for k in HORIZONS],
        "return": [float(th.cat(returns[k]).mean().sqrt()) for k in HORIZONS],
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--episodes", type=int, default=5, help="training episodes (1000 steps each)")
    parser.add_argument("--epochs", type=int, default=20)
    parser.add_argument("--seeds", nargs="+", type=int, default=[0, 1, 2])
    args = parser.parse_args()
    th.set_num_threads(1)
    ks = ", ".join(str(k) for k in HORIZONS)
    print(f"| seed | model | velocity RMSE, k = {ks} | k-step return RMSE, k = {ks} |\n|---|---|---|---|")
    for seed in args.seeds:
        train, held_out = episodes(args.episodes, seed), episodes(2, seed + 1000)
        for hooks in (False, True):
            errors = open_loop_errors(fit(train, hooks, args.epochs, seed), held_out)
            name = "PETS hooks" if hooks else "raw in, deltas out (0.2.0)"
            cells = [" / ".join(f"{v:.3g}" for v in errors[key]) for key in ("velocity", "return")]
            print(f"| {seed} | {name} | {cells[0]} | {cells[1]} |", flush=True)


if __name__ == "__main__":
    main()
