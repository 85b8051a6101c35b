"""
How saturated POPLIN's policy network starts after its first whitening update, per ``whitening`` mode: the share of
first-layer pre-activations beyond ±2 (tanh slope below 0.07) and their mean std per unit, on real HalfCheetah-v5
states (random actions), for five network seeds.

    python benchmarks/whitening_saturation.py [--env HalfCheetah-v5] [--steps 1000]
"""

from __future__ import annotations

import argparse

import numpy as np
import torch as th

from sb3_poplin.policies import WHITENING_MODES, PolicyNetwork
from sb3_poplin.tasks import make_env


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--env", default="HalfCheetah-v5")
    parser.add_argument("--steps", type=int, default=1000)
    parser.add_argument("--seeds", type=int, default=5)
    args = parser.parse_args()
    th.set_num_threads(1)
    env = make_env(args.env)
    obs, _ = env.reset(seed=0)
    env.action_space.seed(0)
    states = []
    for _ in range(args.steps):
        states.append(obs)
        obs, _, terminated, truncated, _ = env.step(env.action_space.sample())
        if terminated or truncated:
            obs, _ = env.reset()
    batch = th.as_tensor(np.array(states), dtype=th.float32)
    action_dim = int(env.action_space.shape[0])
    print("| whitening | pre-activations beyond ±2 | mean std per unit |\n|---|---|---|")
    for mode in WHITENING_MODES:
        beyond, std = [], []
        for seed in range(args.seeds):
            th.manual_seed(seed)
            policy = PolicyNetwork(batch.shape[1], action_dim, (32,))
            policy.update_whitening(batch, mode)
            with th.no_grad():
                pre = policy.whiten(batch) @ policy.weights[0] + policy.biases[0]
            beyond.append(100 * float((pre.abs() > 2).float().mean()))
            std.append(float(pre.std(dim=0).mean()))
        print(f"| `{mode}` | {min(beyond):.1f} to {max(beyond):.1f} % | {min(std):.2f} to {max(std):.2f} |")


if __name__ == "__main__":
    main()
