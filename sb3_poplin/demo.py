"""``python -m sb3_poplin.demo``: the same as ``python -m sb3_poplin.experiments.demo``, the module that holds it."""

import sys

from sb3_poplin.experiments import demo as _module

if __name__ == "__main__":
    _module.main()
else:  # importing sb3_poplin.demo gives the module itself
    sys.modules[__name__] = _module
