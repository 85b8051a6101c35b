"""
The runner: everything that trains, compares and reports, apart from the algorithm.

- :mod:`~sb3_poplin.experiments.zoo`: the rl-zoo3 front end (``sb3-poplin-zoo``: train, enjoy, plots, optimize,
  compare);
- :mod:`~sb3_poplin.experiments.compare`: the head-to-head of algorithms x tasks x seeds (``sb3-poplin-zoo compare``);
- :mod:`~sb3_poplin.experiments.checkpoints`: a training run's checkpoint after every episode and its exact restore;
- :mod:`~sb3_poplin.experiments.presets`: the packaged hyperparameter files and the POPLIN settings read from them;
- :mod:`~sb3_poplin.experiments.demo` (``make demo``) and :mod:`~sb3_poplin.experiments.analysis` (the command line
  of :mod:`sb3_poplin.analysis`).

Only this subpackage parses command lines; the algorithm (:mod:`sb3_poplin.poplin` and what it is built from)
imports nothing of it. ``python -m sb3_poplin.zoo`` and ``python -m sb3_poplin.demo`` stay the entry points (the
modules of those names are these); ``sb3_poplin.compare``, ``sb3_poplin.resume`` and ``sb3_poplin.presets`` are
deprecated aliases (removed in 1.0.0).
"""
