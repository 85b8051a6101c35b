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


BENCHMARKS = Path(__file__).resolve().parent.parent / "benchmarks"


def load_benchmark(name: str) -> ModuleType:
    """
    Import the benchmark script ``name`` as module ``name`` (registered in ``sys.modules``: dataclasses look it up):
    ``benchmarks/<name>.py`` (``results_file``, ``compare``) or ``benchmarks/<folder>/<name>.py`` (``speed``,
    ``diagnosis``, ``probes``; ``benchmarks/README.md`` lists them).
    """
    found = [BENCHMARKS / f"{name}.py", *sorted(BENCHMARKS.glob(f"*/{name}.py"))]
    found = [path for path in found if path.is_file()]
    assert len(found) == 1, f"benchmark script {name!r}: expected one benchmarks/[<folder>/]{name}.py, found {found}"
    path = found[0]
    spec = importlib.util.spec_from_file_location(name, path)
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    sys.modules[name] = module
    spec.loader.exec_module(module)
    return module
