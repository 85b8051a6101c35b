"""``python -m sb3_poplin.experiments.compare``: ``sb3-poplin-zoo compare``."""

import sys

from sb3_poplin.experiments.compare.cli import main

if __name__ == "__main__":
    sys.exit(main())
