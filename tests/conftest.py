"""Shared test set-up: one torch thread (fastest on these 2-core machines), the tiny agent settings, a factory."""

from typing import Any

import torch as th

from sb3_poplin import POPLIN

th.set_num_threads(1)

# the smallest planner and model that still plan and learn something: seconds per episode
TINY: dict[str, Any] = dict(
    horizon=5, population_size=20, num_elites=4, cem_iterations=2, ensemble_size=2, dynamics_net_arch=(16, 16), model_epochs=2
)


def tiny(variant: str = "pets", env: Any = "Pendulum-v1", **kwargs: Any) -> POPLIN:
    """A seeded agent with the :data:`TINY` settings (``kwargs`` override them)."""
    return POPLIN(variant, env, seed=0, **{**TINY, **kwargs})
