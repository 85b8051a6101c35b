"""Shared test set-up: one torch thread (fastest on these 2-core machines), the tiny agent settings, a factory."""

import importlib.util
import sys
from pathlib import Path
from types import ModuleType
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


def load_benchmark(name: str) -> ModuleType:
    """Import ``benchmarks/<name>.py`` as module ``name`` (registered in ``sys.modules``: dataclasses look it up)."""
    path = Path(__file__).resolve().parent.parent / "benchmarks" / f"{name}.py"
    spec = importlib.util.spec_from_file_location(name, path)
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    sys.modules[name] = module
    spec.loader.exec_module(module)
    return module
