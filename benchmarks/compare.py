"""
The head-to-head comparison is the package command ``sb3-poplin-zoo compare`` (``sb3_poplin/experiments/compare/``).

This script is kept so that the commands recorded in ``RESULTS.md`` (``python benchmarks/compare.py ...``) still run
as written: it passes its arguments to that command, unchanged.
"""

import sys

from sb3_poplin.experiments.compare import main

if __name__ == "__main__":
    sys.exit(main())
