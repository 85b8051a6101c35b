"""``python -m sb3_poplin.zoo``: the same as ``python -m sb3_poplin.experiments.zoo``, the module that holds it."""

import sys

from sb3_poplin.experiments import zoo as _module

if __name__ == "__main__":
    _module.main()
else:  # importing sb3_poplin.zoo gives the module itself
    sys.modules[__name__] = _module
