"""
The paper's analyses as tools (Wang & Ba 2019, section 5.3), on your own saved agents:

- :mod:`~sb3_poplin.analysis.surface`: the reward surface a planner searches, in the PCA plane of its candidates,
  with a scale-free roughness number;
- :mod:`~sb3_poplin.analysis.popsize`: planning quality against the population size on a fixed model;
- :mod:`~sb3_poplin.analysis.control`: MPC against policy-control curves from rl-zoo3 runs;
- :mod:`~sb3_poplin.analysis.model_error`: the open-loop k-step error of the learned model on an MPC episode.

Command line: ``python -m sb3_poplin.analysis {surface,popsize,control,model-error} --help``.
"""
