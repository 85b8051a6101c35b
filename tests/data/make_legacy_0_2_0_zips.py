"""
Write a zip of sb3_poplin 0.2.0 (the release before PETSCheetah's model got PETS's hooks) for tests/test_save_load.py.

Run with the 0.2.0 code (commit 4194bb1) on the path, from the repository root (the script's folder, not the working
directory, comes first on ``sys.path``, so the checkout on ``PYTHONPATH`` is imported, not the editable install)::

    mkdir /tmp/sb3p020 && git archive 4194bb1 | tar -x -C /tmp/sb3p020
    PYTHONPATH=/tmp/sb3p020 python tests/data/make_legacy_0_2_0_zips.py tests/data

It writes ``legacy-0.2.0-pets-cheetah.zip`` (a tiny PETS agent on ``sb3_poplin/PETSCheetah-v0``: one random episode,
one model fit, a few planned steps; about 65 KB) and ``legacy-0.2.0-pets-cheetah.npz``: observations, scaled actions,
the next observations that 0.2.0's model predicts for them (expectation over the members) and the actions 0.2.0
plans for the observations right after loading its own zip.
"""

import sys

import gymnasium as gym
import numpy as np
import torch as th
from stable_baselines3.common.callbacks import BaseCallback

import sb3_poplin
from sb3_poplin import POPLIN

CHEETAH = "sb3_poplin/PETSCheetah-v0"
TINY = dict(horizon=4, population_size=16, num_elites=4, cem_iterations=2, ensemble_size=2, dynamics_net_arch=(16, 16))


class StopAt(BaseCallback):
    """Stop training after ``steps`` env steps."""

    def __init__(self, steps: int) -> None:
        super().__init__()
        self.steps = steps

    def _on_step(self) -> bool:
        return self.num_timesteps < self.steps


def cheetah_states(count: int, seed: int) -> np.ndarray:
    """Observations of a random-action episode: the first ``count`` after the reset."""
    env = gym.make(CHEETAH)
    env.action_space.seed(seed)
    states = [env.reset(seed=seed)[0]]
    while len(states) < count:
        states.append(env.step(env.action_space.sample())[0])
    return np.stack(states).astype(np.float32)


def main(out: str) -> None:
    th.set_num_threads(1)
    with open(f"{sb3_poplin.__path__[0]}/version.txt") as file:
        release = file.read().strip()
    assert release == "0.2.0", f"run this with sb3_poplin 0.2.0 on PYTHONPATH, not {release}"
    path = f"{out}/legacy-0.2.0-pets-cheetah.zip"
    model = POPLIN("pets", CHEETAH, seed=0, model_epochs=2, **TINY)
    model.learn(2000, callback=StopAt(1010))  # a random episode, a model fit, 10 planned steps
    model.save(path)

    loaded = POPLIN.load(path)
    obs = cheetah_states(20, seed=1)[::5]  # 4 states along a random episode
    actions = np.random.default_rng(2).uniform(-1.0, 1.0, (len(obs), 6)).astype(np.float32)
    with th.no_grad():
        predicted, _ = loaded.policy.dynamics.propagate(
            th.as_tensor(obs).unsqueeze(1), th.as_tensor(actions).unsqueeze(1), "expectation"
        )
    planned = loaded.predict(obs, episode_start=np.ones(len(obs), dtype=bool))[0]
    np.savez(
        f"{out}/legacy-0.2.0-pets-cheetah.npz",
        obs=obs,
        actions=actions,
        predicted=predicted.squeeze(1).numpy(),
        planned=planned,
    )


if __name__ == "__main__":
    main(sys.argv[1])
