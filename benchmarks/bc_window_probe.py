"""
Why does BC's distilled policy not run on PETSCheetah with the defaults? A probe on the fidelity A/B's trained agents.

The ``v0.3`` BC agents of ``benchmarks/fidelity_ab.py`` keep their distillation data in the saved zip (the window of
the last 10 000 planned steps: states and executed actions, oldest first). This script distills a policy again from
that data in a few ways and evaluates each with policy control on the A/B's evaluation episodes (a fresh env
seeded ``1000 + seed``, deterministic), so the data window is compared on the same planner data, without training
new agents:

- ``saved``: the agent's policy as the A/B evaluated it (the check that the evaluation reproduces the A/B's);
- ``window, fresh``: a freshly initialised network (the saved whitening statistics) cloned onto the whole window;
- ``latest, fresh``: the same network cloned onto the latest episode's steps only (the last ``--episode`` rows);
- ``window, continued`` / ``latest, continued``: the saved policy trained on for one more distillation on each
  (with a new Adam optimizer: the agent's optimizer state is not part of the probe).

- ``saved xG``: the saved policy with its output layer scaled by G (its actions ``clip(G pi(s))``): does the
  cloned network know the direction of the planner's actions and lose only their magnitude, which regression
  onto clipped (bang-bang) targets shrinks where the targets' signs vary?

It also reports the share of the window's executed action entries at the bounds (``|a| = 1``: the planned action was
clipped) and their variance, against which the latest-episode MSE of each clone reads.

And for the agents of both arms (``v0.3``: executed, clipped targets from the window; ``original``: the planned
unclipped targets of the latest episode), the raw output of the policy network on one policy-control episode: the
share of entries beyond ±1 (where the executed action is the bound) and the mean ``|output|``.

Every BC call is the package's ``behaviour_cloning`` with the agent's epochs, batch size and learning rate.

    python benchmarks/bc_window_probe.py --seeds 0 1 2 3
"""

from __future__ import annotations

import argparse
import copy
import json
from pathlib import Path
from typing import Any

import numpy as np
import torch as th
from stable_baselines3.common.evaluation import evaluate_policy
from stable_baselines3.common.monitor import Monitor
from stable_baselines3.common.vec_env import DummyVecEnv

from sb3_poplin import POPLIN
from sb3_poplin.distillation import behaviour_cloning
from sb3_poplin.policies import PolicyNetwork
from sb3_poplin.tasks import make_env

HERE = Path(__file__).resolve().parent
TASK = "sb3_poplin/PETSCheetah-v0"


def model_file(seed: int, arm: str = "v0.3") -> Path:
    return HERE / "fidelity_ab_models" / TASK.replace("/", "_") / "poplin-p_sep_bc" / arm / f"seed{seed}.zip"


def policy_return(model: POPLIN, actor: PolicyNetwork, seed: int, episodes: int) -> list[float]:
    """Policy-control returns of ``actor`` in ``model`` on the A/B's evaluation episodes."""
    saved = model.policy.actor
    model.policy.actor = actor
    model.control = "policy"
    env = DummyVecEnv([lambda: Monitor(make_env(TASK))])
    env.seed(1000 + seed)
    returns, _ = evaluate_policy(model, env, n_eval_episodes=episodes, deterministic=True, return_episode_rewards=True)
    model.policy.actor = saved
    assert isinstance(returns, list)
    return [float(r) for r in returns]


def fresh_like(actor: PolicyNetwork, seed: int) -> PolicyNetwork:
    """A newly initialised network of ``actor``'s shape with ``actor``'s whitening statistics."""
    th.manual_seed(seed)
    net_arch = [b for _, b in actor.shapes[:-1]]
    obs_dim = int(actor.obs_index.max()) + 1
    excluded = sorted(set(range(obs_dim)) - set(actor.obs_index.tolist()))
    fresh = PolicyNetwork(obs_dim, actor.action_dim, net_arch, excluded)
    for name in ("obs_mean", "obs_var", "obs_count"):
        getattr(fresh, name).copy_(getattr(actor, name))
    return fresh


def clone(model: POPLIN, actor: PolicyNetwork, states: th.Tensor, targets: th.Tensor, seed: int) -> dict[str, Any]:
    distiller = model.distiller
    assert distiller is not None
    optimizer = th.optim.Adam(actor.parameters(), lr=model.policy_learning_rate)
    return behaviour_cloning(
        actor,
        optimizer,
        states,
        targets,
        epochs=distiller.epochs,
        batch_size=distiller.batch_size,
        generator=th.Generator().manual_seed(seed),
    )


def probe(seed: int, episodes: int, episode_length: int, gains: list[float]) -> dict[str, Any]:
    model = POPLIN.load(model_file(seed), device="cpu")
    distiller = model.distiller
    assert distiller is not None and distiller.target == "executed" and distiller.data, "a v0.3 BC agent with its window"
    states, targets = distiller.data["states"], distiller.data["actions"]
    latest = slice(states.shape[0] - episode_length, None)
    actor = model.policy.actor
    assert actor is not None
    result: dict[str, Any] = {"seed": seed, "window_rows": int(states.shape[0]), "latest_rows": episode_length}
    result["saved"] = policy_return(model, actor, seed, episodes)
    for gain in gains:
        louder = copy.deepcopy(actor)
        with th.no_grad():
            louder.weights[-1].mul_(gain)
            louder.biases[-1].mul_(gain)
        result[f"saved x{gain:g}"] = policy_return(model, louder, seed, episodes)
    result["targets at the bounds"] = float((targets.abs() >= 1 - 1e-6).float().mean())
    result["target variance"] = float(targets[latest].var(dim=0).mean())
    for data_name, rows in (("window", slice(None)), ("latest", latest)):
        for start in ("fresh", "continued"):
            network = fresh_like(actor, seed) if start == "fresh" else copy.deepcopy(actor)
            stats = clone(model, network, states[rows], targets[rows], seed)
            key = f"{data_name}, {start}"
            result[key] = policy_return(model, network, seed, episodes)
            result[f"{key} holdout loss"] = float(stats.get("policy_holdout_loss", float("nan")))
            with th.no_grad():
                out = network(states[latest])
            # how well the network matches the latest episode's actions, clipped as executed
            result[f"{key} latest-episode MSE"] = float(((out.clamp(-1, 1) - targets[latest]) ** 2).mean())
    return result


def raw_outputs(seed: int, arm: str) -> dict[str, float] | None:
    """One policy-control episode of the ``arm`` agent: its return and its network's raw output statistics."""
    path = model_file(seed, arm)
    if not path.exists():
        return None
    model = POPLIN.load(path, device="cpu")
    actor = model.policy.actor
    assert actor is not None
    model.control = "policy"
    env = make_env(TASK)
    obs, _ = env.reset(seed=1000 + seed)
    raws, total, done = [], 0.0, False
    while not done:
        with th.no_grad():
            raws.append(actor(th.as_tensor(obs, dtype=th.float32)[None])[0])
        action, _ = model.predict(obs, deterministic=True)
        obs, reward, terminated, truncated, _ = env.step(action)
        total += float(reward)
        done = terminated or truncated
    raw = th.stack(raws)
    return {"return": total, "beyond 1": float((raw.abs() > 1).float().mean()), "mean |output|": float(raw.abs().mean())}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--seeds", nargs="+", type=int, default=[0, 1])
    parser.add_argument("--episodes", type=int, default=10, help="policy-control episodes (the A/B's 10)")
    parser.add_argument("--episode", type=int, default=1000, help="rows of the latest episode")
    parser.add_argument("--gains", nargs="+", type=float, default=[3.0, 10.0], help="output gains of the saved policy")
    parser.add_argument("--output", type=Path, default=HERE / "analysis" / "bc_window_probe.json")
    args = parser.parse_args()
    th.set_num_threads(1)
    results = []
    for seed in args.seeds:
        r = probe(seed, args.episodes, args.episode, args.gains)
        r["raw outputs"] = {arm: raw_outputs(seed, arm) for arm in ("v0.3", "original")}
        results.append(r)
        print(
            f"seed {seed} ({r['window_rows']} rows): "
            + ", ".join(f"{k} {np.mean(v):.0f}" for k, v in r.items() if isinstance(v, list))
            + f" | at the bounds {r['targets at the bounds']:.2f}, target variance {r['target variance']:.3f}"
            + " | latest-episode MSE "
            + ", ".join(f"{k.removesuffix(' latest-episode MSE')} {v:.3f}" for k, v in r.items() if k.endswith("MSE")),
            flush=True,
        )
        for arm, stats in r["raw outputs"].items():
            if stats is not None:
                print(f"  {arm} policy, one episode: " + ", ".join(f"{k} {v:.2f}" for k, v in stats.items()), flush=True)
    args.output.write_text(json.dumps(results, indent=1))


if __name__ == "__main__":
    main()
