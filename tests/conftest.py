"""Shared test set-up: one torch thread (fastest on these 2-core machines), the tiny agent settings, a factory."""

import os
import tempfile
from typing import Any

import numpy as np
import torch as th
from hypothesis import settings

from sb3_poplin import POPLIN, kernels

th.set_num_threads(1)

# the forward paths this host chooses (sb3_poplin.kernels) are kept in a throw-away folder, not the user's cache
os.environ[kernels.CACHE_ENV] = tempfile.mkdtemp(prefix="sb3_poplin-test-cache-")

# hypothesis: derandomised, so every run tries the same examples and a failure replays exactly (the examples derive
# from the test itself); HYPOTHESIS_PROFILE=explore draws new ones each run and prints a failure's reproduce blob
settings.register_profile("replayable", derandomize=True, print_blob=True)
settings.register_profile("explore", derandomize=False, print_blob=True)
settings.load_profile(os.environ.get("HYPOTHESIS_PROFILE", "replayable"))

# the smallest planner and model that still plan and learn something: seconds per episode
TINY: dict[str, Any] = dict(
    horizon=5, population_size=20, num_elites=4, cem_iterations=2, ensemble_size=2, dynamics_net_arch=(16, 16), model_epochs=2
)


def tiny(variant: str = "pets", env: Any = "Pendulum-v1", **kwargs: Any) -> POPLIN:
    """A seeded agent with the :data:`TINY` settings (``kwargs`` override them)."""
    return POPLIN(variant, env, seed=0, **{**TINY, **kwargs})


def pendulum_reward(obs: np.ndarray, torque: np.ndarray) -> np.ndarray:
    """Pendulum-v1's reward by hand on pre-step observations ``[..., 3]``: -(theta^2 + 0.1 theta_dot^2 + 0.001 u^2)."""
    theta = np.arctan2(obs[..., 1], obs[..., 0])
    return -(theta**2 + 0.1 * obs[..., 2] ** 2 + 0.001 * np.clip(torque, -2.0, 2.0) ** 2)


def sorted_rows(table: np.ndarray) -> np.ndarray:
    """The rows of a table in lexicographic order: two tables compared as multisets of rows."""
    return table[np.lexsort(table.T[::-1])]
