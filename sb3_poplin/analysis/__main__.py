"""``python -m sb3_poplin.analysis``: the command line is :mod:`sb3_poplin.experiments.analysis`."""

from sb3_poplin.experiments.analysis import main

if __name__ == "__main__":
    main()
