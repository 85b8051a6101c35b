"""Deprecated alias of :mod:`sb3_poplin.experiments.compare` (removed in 1.0.0): import that module instead."""

import sys
import warnings

from sb3_poplin.experiments import compare as _module

if __name__ == "__main__":  # python -m sb3_poplin.compare keeps working
    sys.exit(_module.main())
warnings.warn(
    "sb3_poplin.compare moved to sb3_poplin.experiments.compare (this alias goes in 1.0.0): import it from there.",
    DeprecationWarning,
    stacklevel=2,
)
sys.modules[__name__] = _module
