"""
The head-to-head: POPLIN against the model-free baselines through rl-zoo3, algorithms x tasks x seeds::

    sb3-poplin-zoo compare --algos poplin-p pets sac --envs Pendulum-v1 --seeds 0 1 2 3

Every run is ``sb3-poplin-zoo train`` in its own process (torch on one thread), with the same ``n_timesteps``,
``--eval-freq`` and ``--eval-episodes`` for every algorithm of a task. Runs go to a local pool of ``--jobs``
processes (default 2), or to Ray tasks with ``--ray-address`` (``local`` starts a Ray instance on this machine with
``--jobs`` CPUs; ``auto`` or an address joins a running cluster; Ray is the optional ``ray`` extra).

Runs are resumable. A run whose model and evaluations already exist with the same settings is reused (``--force``
reruns). A run that was interrupted -- the command stopped, the machine rebooted, ``kill -9`` at any moment --
continues from its last checkpoint when the same command is given again: every run saves one after each episode
(:mod:`.checkpoints`: agent, optimizers, replay buffer, planner warm start, distiller, random states, monitor and
evaluation files), and a killed run's folder is found by its settings (``args.yml``) and continued in place, with
nothing recorded twice or lost. Runs that cannot continue exactly (on-policy algorithms, several envs) start again.

``--algos`` takes rl-zoo3 names and POPLIN's variants: ``poplin`` runs the variant of POPLIN's file
(POPLIN-P); ``poplin-p``, ``poplin-a``, ``pets`` and ``rs`` run the zoo algorithm ``poplin`` with that
``policy`` and the task's settings from the same file, each in its own column (``rs`` with a population of
``population_size x cem_iterations``, the candidates CEM evaluates per step).

The report (``--output``) has ``results.md``, a Markdown table of the final evaluation return (mean ± std
over seeds) at the step every algorithm of the task reached, ``results.json`` with the numbers, and
``curves_<task>.png``, one learning-curve figure per task (``/`` in an id becomes ``-``), and ``training_<task>.png``,
its training episodes as the paper plots them. POPLIN-A/P runs
are reported twice: MPC (``evaluations.npz``) and policy control (``evaluations_policy.npz``).

``--suite paper`` runs the POPLIN paper's 13 tasks (``sb3_poplin/tasks/paper_suite.py``: Cheetah, Ant, ...,
Cartpole, Swimmer-v0) under the paper's names: ``--envs`` then picks among them by paper name or id, and the table
is laid out as the paper's, one column per task named as in the paper. Without it (``--suite all``) the tasks are
``--envs`` or every task of the budget's POPLIN file, one row each.

The paper's protocol is reported too: the mean return of the training episodes that ended in the last
``--paper-window`` steps (3000, as the paper) before the task's smallest budget (``paper_protocol`` in
``results.json``, a second table in ``results.md``). ``--steps-scale sac:3 td3:3`` trains those algorithms three times
as long (same evaluation period); the main table stays at the matched step, and a third table gives, per algorithm,
the first step at which its return reached the ``--reference`` column's final one (default ``POPLIN-P (MPC)``), by
evaluation (mean curve over seeds) and by the paper's protocol.

A finished run leaves ``compare_complete.json`` in its folder; with it, the run counts as complete without its
model zip, so a comparison whose small files (``args.yml``, ``config.yml``, ``evaluations*.npz``,
``0.monitor.csv``, the marker) were committed resumes on another machine.

``--budget cpu`` (default) takes POPLIN's settings and each task's ``n_timesteps`` from
``sb3_poplin/hyperparams/poplin_cpu.yml``; ``--budget paper`` from ``poplin.yml``. The baselines use their
packaged files (``sac.yml`` ...) with the same ``n_timesteps``. Smoke test::

    sb3-poplin-zoo compare --algos poplin sac --envs Pendulum-v1 --seeds 0 1 -n 400 --n-evals 2 \\
        --eval-episodes 2 --params poplin:horizon:5 poplin:population_size:20 poplin:num_elites:4

and of the paper suite: ``--suite paper --algos poplin sac --seeds 0 -n 400 ...`` (the same small settings).
"""

from sb3_poplin.experiments.compare.cli import main, parse_args
from sb3_poplin.experiments.compare.execution import execute, execution_order, run_local, run_ray
from sb3_poplin.experiments.presets import BUDGETS
from sb3_poplin.experiments.compare.jobs import (
    ALGOS,
    COMPLETE_FILE,
    PAPER_WINDOW,
    SHORT_EPISODE,
    SHORT_EPISODE_EVALUATIONS,
    SUITES,
    VARIANTS,
    CompareOptions,
    Job,
    JobResult,
    algo_settings,
    evaluation_episodes,
    find_interrupted,
    find_run,
    is_complete,
    job_runs,
    parse_value,
    plan_jobs,
)
from sb3_poplin.experiments.compare.report import (
    Curve,
    ProtocolSummary,
    Reach,
    ReachEntry,
    SeedValues,
    TaskSummary,
    TrainingEpisodes,
    format_cell,
    label_algo,
    load_training,
    summarize,
    training_curve,
    write_report,
)

__all__ = [
    "ALGOS",
    "BUDGETS",
    "COMPLETE_FILE",
    "PAPER_WINDOW",
    "SHORT_EPISODE",
    "SHORT_EPISODE_EVALUATIONS",
    "SUITES",
    "VARIANTS",
    "CompareOptions",
    "Curve",
    "Job",
    "JobResult",
    "ProtocolSummary",
    "Reach",
    "ReachEntry",
    "SeedValues",
    "TaskSummary",
    "TrainingEpisodes",
    "algo_settings",
    "evaluation_episodes",
    "execute",
    "execution_order",
    "find_interrupted",
    "find_run",
    "format_cell",
    "is_complete",
    "job_runs",
    "label_algo",
    "load_training",
    "main",
    "parse_args",
    "parse_value",
    "plan_jobs",
    "run_local",
    "run_ray",
    "summarize",
    "training_curve",
    "write_report",
]
