"""
Write zips with sb3_poplin 0.1.0 (the release before the MPC / Distiller split) for tests/test_save_load.py.
Run with the 0.1.0 code (commit a813380) on the path: ``PYTHONPATH=<its checkout> python make_legacy_zips.py tests/data``.
"""

import sys

import numpy as np
import torch as th
from stable_baselines3.common.callbacks import BaseCallback

from sb3_poplin import POPLIN


class StopAt(BaseCallback):
    def __init__(self, steps):
        super().__init__()
        self.steps = steps

    def _on_step(self):
        return self.num_timesteps < self.steps


th.set_num_threads(1)
TINY = dict(horizon=4, population_size=16, num_elites=4, cem_iterations=2, ensemble_size=2, dynamics_net_arch=(16, 16))
VARIANTS = {"pets": dict(policy="pets"), "poplin-p": dict(policy="poplin-p", distillation="bc", policy_net_arch=[8])}
out = sys.argv[1]
obs = np.array([[0.3, 0.95, -1.0], [-1.0, 0.0, 2.0]], dtype=np.float32)
for name, kwargs in VARIANTS.items():
    model = POPLIN(env="Pendulum-v1", seed=0, model_epochs=2, **TINY, **kwargs)
    model.learn(1000, callback=StopAt(300))  # a random episode, a fit, half a planned episode: steps not yet distilled
    model.save(f"{out}/legacy-0.1.0-{name}.zip")
    starts = np.ones(len(obs), dtype=bool)
    action = POPLIN.load(f"{out}/legacy-0.1.0-{name}.zip").predict(obs, episode_start=starts)[0]
    np.save(f"{out}/legacy-0.1.0-{name}-mpc.npy", action)
