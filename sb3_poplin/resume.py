"""Deprecated alias of :mod:`sb3_poplin.experiments.checkpoints` (removed in 1.0.0): import that module instead."""

import sys
import warnings

from sb3_poplin.experiments import checkpoints as _module

warnings.warn(
    "sb3_poplin.resume moved to sb3_poplin.experiments.checkpoints (this alias goes in 1.0.0): import it from there.",
    DeprecationWarning,
    stacklevel=2,
)
sys.modules[__name__] = _module
