"""
Helpers of the benchmark scripts' tests: importing a script as a module, a tiny agent; and the set-up of
``tests/conftest.py`` (one torch thread, a throw-away cache of the forward paths), so that this folder also runs alone.
"""

from __future__ import annotations

import importlib.util
import os
import sys
import tempfile
from pathlib import Path
from types import ModuleType
from typing import Any

import torch as th

from sb3_poplin import POPLIN, kernels

th.set_num_threads(1)
os.environ.setdefault(kernels.CACHE_ENV, tempfile.mkdtemp(prefix="sb3_poplin-test-cache-"))

BENCHMARKS = Path(__file__).resolve().parent.parent
TINY: dict[str, Any] = dict(
    horizon=5, population_size=20, num_elites=4, cem_iterations=2, ensemble_size=2, dynamics_net_arch=(16, 16), model_epochs=2
)


def load_benchmark(name: str) -> ModuleType:
    """
    Import the benchmark script ``name`` as module ``name`` (registered in ``sys.modules``: dataclasses look it up):
    ``benchmarks/<name>.py`` or ``benchmarks/<folder>/<name>.py`` (``benchmarks/README.md`` lists them).
    """
    found = [BENCHMARKS / f"{name}.py", *sorted(BENCHMARKS.glob(f"*/{name}.py"))]
    found = [path for path in found if path.is_file()]
    assert len(found) == 1, f"benchmark script {name!r}: expected one benchmarks/[<folder>/]{name}.py, found {found}"
    spec = importlib.util.spec_from_file_location(name, found[0])
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    sys.modules[name] = module
    spec.loader.exec_module(module)
    return module


def tiny(variant: str = "pets", env: str = "Pendulum-v1", **kwargs: Any) -> POPLIN:
    """A seeded agent with the :data:`TINY` settings (``kwargs`` override them)."""
    return POPLIN(variant, env, seed=0, **{**TINY, **kwargs})
