"""
Write zips of sb3_poplin 0.3.0 (or of a later release, named as the second argument) on HalfCheetah-v5 for
tests/test_save_load.py: the v5 tasks' model hooks changed after 0.3.0 and 0.4.0 (issue 34), and a zip must keep
loading and planning as it was trained.

Run with the 0.3.0 code (commit 41334bf) on the path, from the repository root (the script's folder, not the working
directory, comes first on ``sys.path``, so the checkout on ``PYTHONPATH`` is imported, not the editable install)::

    mkdir /tmp/sb3p030 && git archive 41334bf | tar -x -C /tmp/sb3p030
    PYTHONPATH=/tmp/sb3p030 python tests/data/make_legacy_0_3_0_zips.py tests/data
    # 0.4.0 (the model on the pitch's sine and cosine, the policy on the raw observation): commit 7123a35
    PYTHONPATH=/tmp/sb3p040 python tests/data/make_legacy_0_3_0_zips.py tests/data 0.4.0
    # Swimmer-v5 with 0.4.1's raw hooks (its hooks changed after 0.4.1): commit 09283f1
    PYTHONPATH=/tmp/sb3p041 python tests/data/make_legacy_0_3_0_zips.py tests/data 0.4.1 Swimmer-v5
    # PETSCheetah with 0.4.2 (the code of the issue-45 headline runs, the last release without a hooks record): 6f0e1cf
    PYTHONPATH=/tmp/sb3p042 python tests/data/make_legacy_0_3_0_zips.py tests/data 0.4.2 sb3_poplin/PETSCheetah-v0
    # the published 0.5.0 (the first release whose zips record their hooks), on both cheetahs: commit 2778ed6
    PYTHONPATH=/tmp/sb3p050 python tests/data/make_legacy_0_3_0_zips.py tests/data 0.5.0 HalfCheetah-v5
    PYTHONPATH=/tmp/sb3p050 python tests/data/make_legacy_0_3_0_zips.py tests/data 0.5.0 sb3_poplin/PETSCheetah-v0

It writes ``legacy-<release>-<variant>-<task>.zip`` (task: ``half-cheetah``, ``swimmer``) for PETS and POPLIN-P
(tiny agents: one random episode, one model fit and distillation, a few planned steps; under 100 KB each) and
``legacy-<release>-<variant>-<task>.npz``: observations (positions kept, as the task makes the env), scaled actions,
the next observations that release's model predicts for them (expectation over the members), the actions it plans for
the observations right after loading its own zip and, for POPLIN-P, its policy network's actions.
"""

import sys

import gymnasium as gym
import numpy as np
import torch as th
from stable_baselines3.common.callbacks import BaseCallback

import sb3_poplin
from sb3_poplin import POPLIN
from sb3_poplin.tasks import make_env

TASK_NAMES = {"HalfCheetah-v5": "half-cheetah", "Swimmer-v5": "swimmer", "sb3_poplin/PETSCheetah-v0": "cheetah"}
TINY = dict(horizon=4, population_size=16, num_elites=4, cem_iterations=2, ensemble_size=2, dynamics_net_arch=(16, 16))


class StopAt(BaseCallback):
    """Stop training after ``steps`` env steps."""

    def __init__(self, steps: int) -> None:
        super().__init__()
        self.steps = steps

    def _on_step(self) -> bool:
        return self.num_timesteps < self.steps


def states(env_id: str, count: int, seed: int) -> np.ndarray:
    """Observations of a random-action episode: the first ``count`` after the reset."""
    env: gym.Env = make_env(env_id)
    env.action_space.seed(seed)
    found = [env.reset(seed=seed)[0]]
    while len(found) < count:
        found.append(env.step(env.action_space.sample())[0])
    return np.stack(found).astype(np.float32)


def main(out: str, expected: str = "0.3.0", env_id: str = "HalfCheetah-v5") -> None:
    th.set_num_threads(1)
    with open(f"{sb3_poplin.__path__[0]}/version.txt") as file:
        release = file.read().strip()
    assert release == expected, f"run this with sb3_poplin {expected} on PYTHONPATH, not {release}"
    for variant in ("pets", "poplin-p"):
        name = f"{out}/legacy-{release}-{variant}-{TASK_NAMES[env_id]}"
        path = f"{name}.zip"
        extra = dict(policy_net_arch=(8,), policy_epochs=2) if variant == "poplin-p" else {}
        model = POPLIN(variant, env_id, seed=0, model_epochs=2, **TINY, **extra)
        model.learn(2000, callback=StopAt(1010))  # a random episode, a model fit, 10 planned steps
        model.save(path)

        loaded = POPLIN.load(path)
        obs = states(env_id, 20, seed=1)[::5]  # 4 states along a random episode
        action_dim = loaded.action_space.shape[0]
        actions = np.random.default_rng(2).uniform(-1.0, 1.0, (len(obs), action_dim)).astype(np.float32)
        with th.no_grad():
            predicted, _ = loaded.policy.dynamics.propagate(
                th.as_tensor(obs).unsqueeze(1), th.as_tensor(actions).unsqueeze(1), "expectation"
            )
        planned = loaded.predict(obs, episode_start=np.ones(len(obs), dtype=bool))[0]
        arrays = dict(obs=obs, actions=actions, predicted=predicted.squeeze(1).numpy(), planned=planned)
        if variant == "poplin-p":
            loaded.control = "policy"
            arrays["policy_actions"] = loaded.predict(obs)[0]
        np.savez(f"{name}.npz", **arrays)


if __name__ == "__main__":
    main(*sys.argv[1:4])
