"""``sb3-poplin-zoo compare``'s command line: the only module of the comparison that sees ``argparse``."""

from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path

from sb3_poplin.experiments.compare.execution import run_local, run_ray
from sb3_poplin.experiments.presets import BUDGETS
from sb3_poplin.experiments.compare.jobs import (
    ALGOS,
    PAPER_WINDOW,
    SHORT_EPISODE,
    SHORT_EPISODE_EVALUATIONS,
    SUITES,
    CompareOptions,
    JobResult,
    find_interrupted,
    find_run,
    plan_jobs,
)
from sb3_poplin.experiments.compare.report import write_report


def _package_doc() -> str:
    """:return: the comparison's documentation (the package's docstring), for ``--help``"""
    return sys.modules["sb3_poplin.experiments.compare"].__doc__ or ""


def parse_args(argv: list[str] | None = None) -> CompareOptions:
    """
    :param argv: the arguments (``None``: ``sys.argv[1:]``)
    :return: the options
    """
    parser = argparse.ArgumentParser(description=_package_doc(), formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--algos", nargs="+", default=list(ALGOS), choices=ALGOS, help="algorithms (rl-zoo3 names)")
    parser.add_argument(
        "--envs",
        nargs="+",
        help="gymnasium ids (default: every task of the budget's POPLIN file); with --suite paper, paper names or ids",
    )
    parser.add_argument(
        "--suite",
        choices=SUITES,
        default="all",
        help="all: --envs or the budget file's tasks; paper: the POPLIN paper's 13 tasks under the paper's names",
    )
    parser.add_argument("--seeds", nargs="+", type=int, default=[0, 1, 2])
    parser.add_argument(
        "--budget", choices=BUDGETS, default="cpu", help="cpu: poplin_cpu.yml and its n_timesteps; paper: poplin.yml"
    )
    parser.add_argument("-n", "--n-timesteps", type=int, help="training steps of every run (default: the budget's)")
    parser.add_argument("--n-evals", type=int, default=10, help="evaluations per run (sets --eval-freq); default 10")
    parser.add_argument("--eval-freq", type=int, help="evaluation period in steps (default: n_timesteps / n_evals)")
    parser.add_argument(
        "--policy-eval-freq",
        type=int,
        help="period of POPLIN-A/P's policy-control evaluation in steps (default: --eval-freq); it plans nothing, so "
        "it can be far more frequent than the MPC evaluation",
    )
    parser.add_argument(
        "--eval-episodes",
        type=int,
        help=f"episodes per evaluation, >= 2 (default: {SHORT_EPISODE_EVALUATIONS} for tasks with episodes of at most "
        f"{SHORT_EPISODE} steps, else 3 with --budget cpu, 5 with paper)",
    )
    parser.add_argument("--jobs", type=int, default=2, help="parallel runs (local pool, or CPUs of a local Ray instance)")
    parser.add_argument("--ray-address", help="run as Ray tasks: 'local' (new local instance), 'auto' or a cluster address")
    parser.add_argument("--params", nargs="+", default=[], help="-params overrides per algorithm: ALGO:KEY:VALUE")
    parser.add_argument(
        "--steps-scale",
        nargs="+",
        default=[],
        help="ALGO:FACTOR: train ALGO FACTOR times the task's budget (e.g. sac:3 td3:3), same evaluation period",
    )
    parser.add_argument(
        "--paper-window",
        type=int,
        default=PAPER_WINDOW,
        help="the paper's protocol: mean return of the training episodes of the last N steps (default 3000)",
    )
    parser.add_argument(
        "--reference",
        default="POPLIN-P (MPC)",
        help="the column whose final return the others must reach (steps-to-reach table; default 'POPLIN-P (MPC)')",
    )
    parser.add_argument(
        "--protocol-steps",
        type=int,
        nargs="+",
        default=[],
        help="also report the paper's protocol at these steps (e.g. 15000 25000 35000 50000), each seed's value too",
    )
    parser.add_argument("--log-folder", help="rl-zoo3 log folder (default: logs/compare-<budget>)")
    parser.add_argument("--output", help="report folder (default: <log folder>/report)")
    parser.add_argument("--python", default=sys.executable, help="interpreter of the runs (default: this one)")
    parser.add_argument(
        "--keep-learning-starts",
        action="store_true",
        help="keep the baselines' learning_starts even when it is half the budget or more (default: a tenth of it)",
    )
    parser.add_argument("--force", action="store_true", help="train again even when a complete run exists")
    parser.add_argument("--report-only", action="store_true", help="do not train: report the complete runs that exist")
    parser.add_argument(
        "--include-unfinished",
        action="store_true",
        help="with --report-only: also report the interrupted runs, as far as they got (marked in the report)",
    )
    options = parser.parse_args(argv)
    if options.eval_episodes is not None and options.eval_episodes < 2:
        parser.error("--eval-episodes must be >= 2 (rl-zoo3's all_plots needs it)")
    if options.jobs < 1 or options.n_evals < 1 or options.paper_window < 1:
        parser.error("--jobs, --n-evals and --paper-window must be >= 1")
    if any(step < 1 for step in options.protocol_steps):
        parser.error("--protocol-steps takes environment steps >= 1")
    if options.include_unfinished and not options.report_only:
        parser.error("--include-unfinished reports runs as they stand: use it with --report-only")
    if options.policy_eval_freq is not None and options.policy_eval_freq < 1:
        parser.error("--policy-eval-freq must be >= 1")
    return CompareOptions(**vars(options))


def main(argv: list[str] | None = None) -> int:
    """
    Plan, run and report a comparison.

    :param argv: the arguments (``None``: ``sys.argv[1:]``)
    :return: the exit code: 1 when a run failed or is missing
    """
    options = parse_args(argv)
    jobs = plan_jobs(options)
    print(f"{len(jobs)} runs ({len(options.algos)} algorithms x {len(options.tasks())} tasks x {len(options.seeds)} seeds)")
    if options.report_only:
        results = []
        for job in jobs:
            run_dir, unfinished = find_run(job), False
            if run_dir is None and options.include_unfinished:
                run_dir = find_interrupted(job)
                unfinished = run_dir is not None
            result = JobResult(job, 0 if run_dir else 1, run_dir, reused=run_dir is not None, missing=not run_dir)
            result.unfinished = unfinished
            results.append(result)
    elif options.ray_address:
        results = run_ray(jobs, options.ray_address, options.jobs, options.force)
    else:
        results = run_local(jobs, options.jobs, options.force)
    output = Path(options.output or os.path.join(jobs[0].log_folder if jobs else ".", "report"))
    table = write_report(
        results,
        options.tasks(),
        options.budget,
        output,
        options.paper_names,
        options.paper_window,
        options.reference,
        options.protocol_steps,
    )
    print(table.read_text())
    print(f"Report: {output}")
    n_missing = sum(result.run_dir is None and result.missing for result in results)
    n_failed = sum(result.run_dir is None and not result.missing for result in results)
    if n_failed:
        print(f"{n_failed} of {len(results)} runs failed (see {jobs[0].log_folder}/compare_logs)")
    n_unfinished = sum(result.unfinished for result in results)
    if n_missing:
        print(f"{n_missing} of {len(results)} runs are missing: --report-only reports complete runs, run without it")
    if n_unfinished:
        print(f"{n_unfinished} of {len(results)} runs are unfinished: reported as far as they got")
    return 1 if n_failed or n_missing else 0


if __name__ == "__main__":
    sys.exit(main())
