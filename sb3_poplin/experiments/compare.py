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
``curves_<task>.png``, one learning-curve figure per task (``/`` in an id becomes ``-``). POPLIN-A/P runs
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

from __future__ import annotations

import argparse
import concurrent.futures
import ctypes
import json
import os
import signal
import subprocess
import sys
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np
import yaml

from sb3_poplin.experiments.presets import HYPERPARAMS_DIR, PACKAGED_ALGOS
from sb3_poplin.experiments.checkpoints import CHECKPOINT_FOLDER, latest_checkpoint
from sb3_poplin.tasks.paper_suite import PAPER_TASKS
from sb3_poplin.variants import DEFAULT_SETTINGS, POLICY_VARIANTS
from sb3_poplin.variants import VARIANTS as VARIANT_TABLE

# POPLIN variants run as the zoo algorithm "poplin" with ``policy`` set; "poplin" alone is the file's variant
VARIANTS = tuple(VARIANT_TABLE)
ALGOS = ("poplin", *VARIANTS, *(algo for algo in PACKAGED_ALGOS if algo != "poplin"))
BUDGETS = ("cpu", "paper")
SUITES = ("all", "paper")
# files of a run directory sent back by a Ray task (for clusters without a shared file system)
RUN_FILE_SUFFIXES = (".npz", ".yml", ".txt", ".csv", ".zip", ".json")
# written into a run's folder when the run finished (a run with it is complete without its model zip)
COMPLETE_FILE = "compare_complete.json"
# the paper's protocol: the training episodes of the last 3000 steps
PAPER_WINDOW = 3000
# evaluations of tasks with episodes of at most SHORT_EPISODE steps average at least SHORT_EPISODE_EVALUATIONS episodes
# (200 steps or fewer; 201 lets the MBBL tasks' 201-step episodes count as what they are)
SHORT_EPISODE = 201
SHORT_EPISODE_EVALUATIONS = 10


def hyperparams_dir() -> Path:
    """The packaged ``sb3_poplin/hyperparams`` folder."""
    return HYPERPARAMS_DIR


def paper_suite_envs(selected: list[str] | None) -> dict[str, str]:
    """
    :param selected: paper names or env ids to keep (``None``: all 13)
    :return: env id -> the paper's name, in the paper's order
    """
    tasks = PAPER_TASKS
    names = {task.env_id: name for name, task in tasks.items()}
    if selected is None:
        return names
    unknown = [item for item in selected if item not in tasks and item not in names]
    if unknown:
        raise SystemExit(f"--suite paper: {unknown} are not paper tasks; use names from {list(tasks)} or their env ids.")
    chosen = {tasks[item].env_id if item in tasks else item for item in selected}
    return {env: name for env, name in names.items() if env in chosen}


def env_name(env: str) -> str:
    """
    :param env: gymnasium id
    :return: the name rl-zoo3 gives it in its folders (``/`` becomes ``-``, as ``huggingface_sb3`` does)
    """
    return env.replace("/", "-")


def read_yaml(path: Path) -> dict[str, Any]:
    """
    :param path: a YAML file
    :return: its mapping (empty when it holds none)
    """
    with open(path) as file:
        content = yaml.safe_load(file)
    return content if isinstance(content, dict) else {}


def parse_value(text: str) -> Any:
    """
    :param text: a ``-params`` value
    :return: the value as rl-zoo3 reads it (a Python expression)
    """
    return eval(text)  # the zoo evaluates the same string


def conf_identity(path: str | None) -> str | None:
    """
    :param path: a hyperparameter file as a run's ``args.yml`` records it (absolute, so it names the checkout)
    :return: what identifies the file across checkouts and machines: a packaged file (``sb3_poplin/hyperparams/X``)
        by that tail, any other file by its resolved path
    """
    if path is None:
        return None
    parts = Path(path).parts
    if len(parts) >= 3 and parts[-3:-1] == ("sb3_poplin", "hyperparams"):
        return "/".join(parts[-3:])
    return str(Path(path).resolve())


def same_settings(expected: dict[str, Any], recorded: dict[str, Any]) -> bool:
    """
    :param expected: a job's ``-params`` values
    :param recorded: what the run's ``args.yml`` recorded for them
    :return: whether they are the same settings: the same keys and values, except that rl-zoo3 adds keys to a dict
        value it was given (``use_sde: False`` into SAC's ``policy_kwargs``), so a recorded dict value may hold more keys
        than the expected one, never other values
    """

    def same_value(want: Any, got: Any) -> bool:
        if isinstance(want, dict) and isinstance(got, dict):
            return set(want) <= set(got) and all(same_value(value, got[key]) for key, value in want.items())
        return bool(want == got)

    return set(expected) == set(recorded) and all(same_value(value, recorded[key]) for key, value in expected.items())


@dataclass
class Job:
    """
    One training run.

    :param algo: rl-zoo3 algorithm name, or a POPLIN variant (``poplin-p``, ``pets`` ...)
    :param env: gymnasium id
    :param seed: random seed
    :param n_timesteps: training steps
    :param eval_freq: evaluation period in steps
    :param eval_episodes: episodes per evaluation
    :param conf_file: hyperparameter file, or ``None`` for the zoo's own
    :param params: ``-params`` overrides, as ``KEY:VALUE`` strings
    :param log_folder: rl-zoo3 log folder (absolute)
    :param python: interpreter that runs the zoo
    :param policy_eval_freq: period of the policy-control evaluation of POPLIN-A/P runs (``None``: ``eval_freq``)
    """

    algo: str
    env: str
    seed: int
    n_timesteps: int
    eval_freq: int
    eval_episodes: int
    conf_file: str | None
    params: list[str]
    log_folder: str
    python: str
    policy_eval_freq: int | None = None

    @property
    def zoo_algo(self) -> str:
        """The rl-zoo3 algorithm of the run (``poplin`` for every POPLIN variant)."""
        return "poplin" if self.algo in VARIANTS else self.algo

    @property
    def column(self) -> str:
        """The report's name of the algorithm: the POPLIN variant that runs (``-params``, else the file's)."""
        if self.zoo_algo != "poplin":
            return self.algo
        for setting in self.params:
            if setting.startswith("policy:"):
                return str(parse_value(setting.split(":", 1)[1]))
        entry = read_yaml(Path(self.conf_file)).get(self.env, {}) if self.conf_file else {}
        return str(entry.get("policy", self.algo))

    @property
    def name(self) -> str:
        """A file-name-safe name of the job."""
        return f"{self.algo}_{env_name(self.env)}_seed{self.seed}"

    def command(self, resume: str | None = None) -> list[str]:
        """
        :param resume: the folder of an interrupted run of this job to continue (relative to the log folder)
        :return: the command line of the run (it saves a checkpoint after every episode)
        """
        command = [self.python, "-m", "sb3_poplin.experiments.zoo", "train", "--algo", self.zoo_algo, "--env", self.env]
        command += ["--seed", str(self.seed), "-f", self.log_folder, "-uuid", "--num-threads", "1", "--checkpoints"]
        if resume is not None:
            command += ["--resume", os.path.join(self.log_folder, resume)]
        command += ["-n", str(self.n_timesteps), "--eval-freq", str(self.eval_freq)]
        command += ["--eval-episodes", str(self.eval_episodes)]
        if self.policy_eval_freq is not None:
            command += ["--policy-eval-freq", str(self.policy_eval_freq)]
        if self.conf_file is not None:
            command += ["--conf-file", self.conf_file]
        if self.params:
            command += ["-params", *self.params]
        return command

    def matches(self, args: dict[str, Any]) -> bool:
        """
        :param args: a run's ``args.yml``
        :return: whether this job's command wrote it
        """
        expected = {key.split(":", 1)[0]: parse_value(key.split(":", 1)[1]) for key in self.params}
        return (
            args.get("algo") == self.zoo_algo
            and args.get("env") == self.env
            and args.get("seed") == self.seed
            and args.get("n_timesteps") == self.n_timesteps
            and args.get("eval_freq") == self.eval_freq
            and args.get("eval_episodes") == self.eval_episodes
            and args.get("policy_eval_freq") == self.policy_eval_freq
            and conf_identity(args.get("conf_file")) == conf_identity(self.conf_file)
            and same_settings(expected, args.get("hyperparams") or {})
        )


@dataclass
class JobResult:
    """
    :param job: the job
    :param returncode: exit code of the run (0 for a reused run)
    :param run_dir: the run's folder relative to the log folder, or ``None`` when not found
    :param reused: an existing run was reused
    :param resumed: the interrupted run that was continued (relative path), if any
    :param output_tail: the end of the run's output (for failures)
    :param files: run files sent back by a Ray task (relative path -> content)
    :param missing: no complete run exists and none was started (``--report-only``): reported as missing, not failed
    """

    job: Job
    returncode: int
    run_dir: str | None = None
    reused: bool = False
    resumed: str | None = None
    output_tail: str = ""
    files: dict[str, bytes] = field(default_factory=dict)
    missing: bool = False


def is_complete(run: Path, name: str) -> bool:
    """
    :param run: a run's folder
    :param name: the env's folder name
    :return: whether the run finished: it has the completion marker, or its model and no checkpoints left (a
        run drops its checkpoints when it finishes training; one stopped by Ctrl-C saves its model but keeps them)
    """
    if (run / COMPLETE_FILE).is_file():
        return True
    finished = (run / f"{name}.zip").is_file() and not (run / CHECKPOINT_FOLDER).exists()
    return finished and (run / "evaluations.npz").is_file()


def job_runs(job: Job) -> list[tuple[float, Path, bool]]:
    """
    :param job: the job
    :return: the run folders this job's command wrote (``args.yml`` matches): modification time, folder, complete
    """
    root = Path(job.log_folder) / job.zoo_algo
    if not root.is_dir():
        return []
    name = env_name(job.env)
    found: list[tuple[float, Path, bool]] = []
    for run in root.iterdir():
        args_file = run / name / "args.yml"
        if not (run.name.startswith(f"{name}_") and args_file.is_file()):
            continue
        try:
            with open(args_file) as file:
                args = yaml.load(file, Loader=yaml.UnsafeLoader)  # written by the zoo (an OrderedDict)
        except yaml.YAMLError as error:
            print(f"warning: {args_file} is unreadable ({type(error).__name__}); that run folder is ignored")
            continue
        if isinstance(args, dict) and job.matches(dict(args)):
            found.append((run.stat().st_mtime, run, is_complete(run, name)))
    return found


def find_run(job: Job) -> str | None:
    """
    :param job: the job
    :return: the newest complete run of ``job`` in its log folder (relative path), or ``None``
    """
    complete = [(mtime, run) for mtime, run, done in job_runs(job) if done]
    if not complete:
        return None
    return str(max(complete)[1].relative_to(job.log_folder))


def find_interrupted(job: Job) -> str | None:
    """
    :param job: the job
    :return: the interrupted run of ``job`` to continue (relative path): the one with the newest checkpoint, else
        the newest one; ``None`` when there is none
    """
    interrupted = [(mtime, run) for mtime, run, done in job_runs(job) if not done]
    if not interrupted:
        return None

    def progress(item: tuple[float, Path]) -> tuple[int, float]:
        checkpoint = latest_checkpoint(item[1])
        return (int(checkpoint.name.split("-", 1)[1]) if checkpoint is not None else -1, item[0])

    return str(max(interrupted, key=progress)[1].relative_to(job.log_folder))


def _load_prctl() -> Any:
    """:return: Linux's ``prctl`` (resolved here, not in the forked child), or ``None`` elsewhere"""
    try:
        return ctypes.CDLL(None, use_errno=True).prctl
    except (OSError, AttributeError):
        return None


_PRCTL = _load_prctl()
PR_SET_PDEATHSIG = 1


def _die_with_parent() -> None:
    """In a run's process (Linux): be killed when the comparison's process dies, so no orphan trains on."""
    if _PRCTL is not None:
        _PRCTL(PR_SET_PDEATHSIG, signal.SIGKILL)


def mark_complete(job: Job, run_dir: str) -> None:
    """
    Write the completion marker into a finished run's folder (if it has none), so that its small files alone make it
    complete (a committed run folder, whose zips git ignores).

    :param job: the job
    :param run_dir: its finished run (relative to the log folder)
    """
    path = Path(job.log_folder) / run_dir / COMPLETE_FILE
    if not path.is_file():
        marker = {"job": job.name, "command": job.command()[1:], "n_timesteps": job.n_timesteps}
        path.write_text(json.dumps(marker, indent=1))


def execute(job: Job, force: bool = False, collect_files: bool = False) -> JobResult:
    """
    Run one job (or reuse its complete run).

    :param job: the job
    :param force: train again even if a complete run exists
    :param collect_files: return the run's files (Ray tasks on machines without a shared file system)
    :return: the outcome
    """
    run_dir = None if force else find_run(job)
    result = JobResult(job, 0, run_dir, reused=run_dir is not None)
    if run_dir is not None:
        mark_complete(job, run_dir)  # a comparison killed after the run finished did not mark it
    else:
        interrupted = None if force else find_interrupted(job)
        os.makedirs(os.path.join(job.log_folder, "compare_logs"), exist_ok=True)
        log_file = os.path.join(job.log_folder, "compare_logs", f"{job.name}.log")
        env = dict(os.environ, OMP_NUM_THREADS="1", MKL_NUM_THREADS="1")
        command = job.command(resume=interrupted)
        with open(log_file, "a" if interrupted else "w") as output:
            if interrupted:
                output.write(f"\n--- continuing the interrupted run {interrupted} ---\n")
                output.flush()
            process = subprocess.run(
                command, stdout=output, stderr=subprocess.STDOUT, env=env, check=False, preexec_fn=_die_with_parent
            )
        result.returncode = process.returncode
        result.resumed = interrupted
        result.run_dir = find_run(job) if process.returncode == 0 else None
        if result.run_dir is not None:
            mark_complete(job, result.run_dir)
        else:
            with open(log_file) as output:
                result.output_tail = "".join(output.readlines()[-30:])
            result.returncode = result.returncode or 1
    if collect_files and result.run_dir is not None:
        run_path = Path(job.log_folder) / result.run_dir
        for path in run_path.rglob("*"):
            if path.is_file() and path.suffix in RUN_FILE_SUFFIXES:
                result.files[str(path.relative_to(job.log_folder))] = path.read_bytes()
    return result


def run_local(jobs: list[Job], n_parallel: int, force: bool) -> list[JobResult]:
    """
    Run the jobs in a pool of ``n_parallel`` processes.

    :param jobs: the jobs
    :param n_parallel: runs at a time
    :param force: train again even if a complete run exists
    :return: the results, in the jobs' order
    """
    futures: dict[int, concurrent.futures.Future[JobResult]] = {}
    with concurrent.futures.ThreadPoolExecutor(max_workers=n_parallel) as pool:
        for index in execution_order(jobs):
            futures[index] = pool.submit(execute, jobs[index], force)
        for future in concurrent.futures.as_completed(futures.values()):
            report_progress(future.result())
    return [futures[index].result() for index in range(len(jobs))]


def execution_order(jobs: list[Job]) -> list[int]:
    """
    The order in which runs start: seed by seed, each seed's algorithms together (task by task), so that the
    algorithms' first seeds finish first and a partial comparison is a paired one.

    :param jobs: the jobs (algorithm-major, as :func:`plan_jobs` makes them)
    :return: indices into ``jobs``
    """
    seeds = sorted({job.seed for job in jobs})
    return sorted(range(len(jobs)), key=lambda index: (seeds.index(jobs[index].seed), index))


def run_ray(jobs: list[Job], address: str, n_parallel: int, force: bool) -> list[JobResult]:
    """
    Run the jobs as Ray tasks of one CPU each; the files of runs made on other machines are written to the
    local log folder. Complete runs in the local log folder are reused without a task. An interrupted run continues
    from its checkpoint only where the node that runs it sees the run's folder (a shared file system); elsewhere it
    starts again.

    :param jobs: the jobs
    :param address: ``"local"`` (start a Ray instance here), ``"auto"`` or a cluster address
    :param n_parallel: CPUs of a local Ray instance
    :param force: train again even if a complete run exists
    :return: the results, in the jobs' order
    """
    try:
        import ray
    except ImportError:
        raise SystemExit("--ray-address needs Ray: pip install 'sb3_poplin[ray]'") from None
    if address == "local":
        ray.init(num_cpus=n_parallel, include_dashboard=False, log_to_driver=False)
    else:
        ray.init(address=address, log_to_driver=False)
    try:
        task = ray.remote(num_cpus=1)(execute)
        remote: Any = task.remote  # Ray's stubs type a remote function by its first signature only
        results: dict[int, JobResult] = {}
        submitted = {}
        for index, job in enumerate(jobs):
            local = None if force else find_run(job)
            if local is not None:  # complete here: the nodes need not see this folder
                results[index] = JobResult(job, 0, local, reused=True)
                mark_complete(job, local)
                report_progress(results[index])
            else:
                submitted[remote(job, force, True)] = index
        pending = list(submitted)
        while pending:
            done, pending = ray.wait(pending, num_returns=1)
            result = ray.get(done[0])
            for relative, content in result.files.items():
                path = Path(result.job.log_folder) / relative
                if not path.exists():
                    path.parent.mkdir(parents=True, exist_ok=True)
                    path.write_bytes(content)
            result.files = {}
            report_progress(result)
            results[submitted[done[0]]] = result
    finally:
        ray.shutdown()
    return [results[index] for index in range(len(jobs))]


def report_progress(result: JobResult) -> None:
    """
    :param result: a finished job, printed as one line (with the end of its output when it failed)
    """
    if result.returncode == 0:
        state = "reused" if result.reused else "resumed" if result.resumed else "done"
        print(f"[{state}] {result.job.name}: {result.run_dir}", flush=True)
    else:
        print(f"[failed {result.returncode}] {result.job.name}\n{result.output_tail}", flush=True)


# ------------------------------------------------------------------------------------------------- report
@dataclass
class Curve:
    """
    Evaluation results of one run under one label.

    :param label: row label, e.g. ``"SAC"`` or ``"POPLIN-P (policy)"``
    :param seed: the run's seed
    :param timesteps: evaluation steps
    :param returns: mean evaluation return at each of them
    """

    label: str
    seed: int
    timesteps: np.ndarray
    returns: np.ndarray


def load_curves(result: JobResult) -> list[Curve]:
    """
    :param result: a finished job with a run
    :return: its evaluation curves: one, or two (MPC and policy) for POPLIN-A/P
    """
    job = result.job
    assert result.run_dir is not None
    run = Path(job.log_folder) / result.run_dir
    files = {job.algo.upper(): run / "evaluations.npz"}
    if job.zoo_algo == "poplin":
        with open(run / env_name(job.env) / "config.yml") as file:
            config = yaml.load(file, Loader=yaml.UnsafeLoader)  # written by the zoo (an OrderedDict)
        variant = str(dict(config).get("policy", "poplin")).upper()
        files = {f"{variant} (MPC)": run / "evaluations.npz"}
        if variant.lower() in POLICY_VARIANTS:
            files[f"{variant} (policy)"] = run / "evaluations_policy.npz"
    curves = []
    for label, path in files.items():
        if not path.is_file():
            continue
        with np.load(path) as data:
            timesteps, results = np.asarray(data["timesteps"]), np.asarray(data["results"], dtype=float)
        if len(timesteps):
            curves.append(Curve(label, job.seed, timesteps, results.reshape(len(timesteps), -1).mean(axis=1)))
    return curves


@dataclass
class TrainingEpisodes:
    """
    The training episodes of one run (its monitor files), for the paper's protocol.

    :param label: the algorithm's label, e.g. ``"POPLIN-P"`` or ``"SAC"``
    :param seed: the run's seed
    :param end_steps: the environment step at which each episode ended
    :param returns: each episode's return
    """

    label: str
    seed: int
    end_steps: np.ndarray
    returns: np.ndarray

    def window_mean(self, step: int, window: int) -> float:
        """
        :param step: environment step
        :param window: steps
        :return: the mean return of the episodes that ended in ``(step - window, step]`` (``nan`` when none did)
        """
        inside = (self.end_steps > step - window) & (self.end_steps <= step)
        return float(self.returns[inside].mean()) if inside.any() else float("nan")


def load_training(result: JobResult) -> TrainingEpisodes | None:
    """
    :param result: a finished job with a run
    :return: its training episodes (from ``*.monitor.csv``; several envs merged in the order the episodes ended), or
        ``None`` when the run has no monitor file
    """
    job = result.job
    assert result.run_dir is not None
    rows = []
    for path in sorted((Path(job.log_folder) / result.run_dir).glob("*.monitor.csv")):
        data = np.loadtxt(path, delimiter=",", skiprows=2, ndmin=2)  # a JSON comment line, then "r,l,t"
        rows += [tuple(row[:3]) for row in data]
    if not rows:
        return None
    rows.sort(key=lambda row: row[2])
    returns, lengths, _ = (np.asarray(column, dtype=float) for column in zip(*rows, strict=True))
    return TrainingEpisodes(job.column.upper(), job.seed, np.cumsum(lengths).astype(int), returns)


def first_step_reaching(steps: np.ndarray, values: np.ndarray, target: float) -> int | None:
    """
    :param steps: increasing environment steps
    :param values: a return at each of them (``nan``: not defined yet)
    :param target: the return to reach
    :return: the first step whose value is at least ``target`` (``None``: never)
    """
    reached = np.flatnonzero(np.nan_to_num(values, nan=-np.inf) >= target)
    return int(steps[reached[0]]) if len(reached) else None


def reach_entry(steps: np.ndarray, per_seed: list[np.ndarray], seeds: list[int], target: float) -> dict[str, Any]:
    """
    :param steps: the steps shared by the seeds' curves
    :param per_seed: each seed's return at those steps
    :param seeds: the seeds
    :param target: the return to reach
    :return: the first step of the mean curve (over seeds) and of each seed's curve that reached ``target``
    """
    mean = np.mean(np.stack(per_seed), axis=0)
    pairs = zip(seeds, per_seed, strict=True)
    return {
        "step": first_step_reaching(steps, mean, target),
        "per_seed": {str(seed): first_step_reaching(steps, values, target) for seed, values in pairs},
        "last_step": int(steps[-1]),
    }


def value_at(curve: Curve, step: int) -> float:
    """
    :param curve: evaluation curve
    :param step: environment step
    :return: the curve's return at its last evaluation at or before ``step``
    """
    index = int(np.searchsorted(curve.timesteps, step, side="right")) - 1
    return float(curve.returns[max(index, 0)])


def summarize(
    env: str,
    curves: list[Curve],
    failed: dict[str, int],
    expected: dict[str, int],
    training: list[TrainingEpisodes] | None = None,
    budget_step: int | None = None,
    window: int = PAPER_WINDOW,
    reference: str | None = None,
    missing: dict[str, int] | None = None,
) -> dict[str, Any]:
    """
    Final returns of one task at the matched step (the last evaluation step every run reached), by the paper's
    protocol at the task's smallest budget, and the steps at which each column reached the reference's final return.

    :param env: gymnasium id
    :param curves: the task's curves
    :param failed: algorithm -> failed runs
    :param expected: algorithm -> planned runs
    :param training: the task's training episodes (one per run)
    :param budget_step: the step of the paper's protocol (the task's smallest ``n_timesteps``)
    :param window: the paper's protocol averages the training episodes that ended in the last ``window`` steps
    :param reference: the column whose final return the others must reach (``None`` or absent: no reach table)
    :param missing: algorithm -> runs not found and not started (``--report-only``)
    :return: the summary written to ``results.json``
    """
    matched = int(min(curve.timesteps[-1] for curve in curves)) if curves else 0
    labels: dict[str, dict[str, Any]] = {}
    for curve in curves:
        entry = labels.setdefault(curve.label, {"seeds": [], "final": []})
        entry["seeds"].append(curve.seed)
        entry["final"].append(value_at(curve, matched))
    for entry in labels.values():
        entry["mean"] = float(np.mean(entry["final"]))
        entry["std"] = float(np.std(entry["final"]))
    summary: dict[str, Any] = {"env": env, "matched_step": matched, "labels": labels, "failed": failed, "expected": expected}
    summary["missing"] = dict(missing or {})
    training = training or []
    paper: dict[str, dict[str, Any]] = {}
    if budget_step is not None:
        for episodes in training:
            value = episodes.window_mean(budget_step, window)
            if not np.isnan(value):
                entry = paper.setdefault(episodes.label, {"seeds": [], "values": []})
                entry["seeds"].append(episodes.seed)
                entry["values"].append(value)
        for entry in paper.values():
            entry["mean"] = float(np.mean(entry["values"]))
            entry["std"] = float(np.std(entry["values"]))
    summary["paper_protocol"] = {"step": budget_step, "window": window, "labels": paper}
    if reference is None or reference not in labels:
        return summary
    reach: dict[str, Any] = {"reference": reference, "target": labels[reference]["mean"], "evaluation": {}}
    for label in labels:
        runs = [curve for curve in curves if curve.label == label]
        length = min(len(curve.timesteps) for curve in runs)
        values = [curve.returns[:length] for curve in runs]
        reach["evaluation"][label] = reach_entry(runs[0].timesteps[:length], values, [c.seed for c in runs], reach["target"])
    paper_reference = paper.get(label_algo(reference).upper())
    if paper_reference is not None:
        reach["paper_target"] = paper_reference["mean"]
        reach["paper_protocol"] = {}
        for label in dict.fromkeys(episodes.label for episodes in training):
            trained = [episodes for episodes in training if episodes.label == label]
            steps = np.unique(np.concatenate([episodes.end_steps for episodes in trained]))
            values = [np.array([episodes.window_mean(int(step), window) for step in steps]) for episodes in trained]
            seeds = [episodes.seed for episodes in trained]
            reach["paper_protocol"][label] = reach_entry(steps, values, seeds, reach["paper_target"])
    summary["reach"] = reach
    return summary


def format_cell(summary: dict[str, Any], label: str, algo: str) -> str:
    """
    :param summary: a task's summary
    :param label: column label
    :param algo: the label's algorithm
    :return: the table cell: mean ± std over seeds, the number of seeds, of failed runs and of missing ones (not run
        yet: ``--report-only``)
    """
    entry = summary["labels"].get(label)
    absent = {"failed": summary["failed"].get(algo, 0), "missing": summary.get("missing", {}).get(algo, 0)}
    note = "".join(f", {count} {kind}" for kind, count in absent.items() if count)
    if entry is None:
        expected = summary["expected"].get(algo, 0)
        return ", ".join(f"{kind} ({count}/{expected})" for kind, count in absent.items() if count) or "—"
    n_seeds = len(entry["final"])
    if n_seeds == 1:
        return f"{entry['mean']:.1f} (1 seed{note})"
    return f"{entry['mean']:.1f} ± {entry['std']:.1f} ({n_seeds} seeds{note})"


def label_algo(label: str) -> str:
    """
    :param label: column label, e.g. ``"POPLIN-P (MPC)"`` or ``"SAC"``
    :return: its algorithm (a POPLIN variant for POPLIN's columns), as ``Job.column`` names it
    """
    return label.removesuffix(" (MPC)").removesuffix(" (policy)").lower()


def table_labels(summaries: list[dict[str, Any]]) -> list[str]:
    """
    :param summaries: one per task
    :return: every algorithm label of the report, in order of appearance (an algorithm whose every run failed too)
    """
    labels: list[str] = []
    for summary in summaries:
        labels += [label for label in summary["labels"] if label not in labels]
    for summary in summaries:
        for algo in [*summary["failed"], *summary.get("missing", {})]:
            if not any(label_algo(label) == algo for label in labels):
                labels.append(algo.upper())
    return labels


def _mean_cell(entry: dict[str, Any] | None, key: str) -> str:
    if entry is None:
        return "—"
    n_seeds = len(entry[key])
    return f"{entry['mean']:.1f} ± {entry['std']:.1f} ({n_seeds} seed{'s' if n_seeds > 1 else ''})"


def _reach_cell(entry: dict[str, Any] | None) -> str:
    if entry is None:
        return "—"
    per_seed = ", ".join(f"s{seed}: {'—' if step is None else step}" for seed, step in entry["per_seed"].items())
    first = f"not by {entry['last_step']}" if entry["step"] is None else str(entry["step"])
    return f"{first} ({per_seed})"


def protocol_lines(summaries: list[dict[str, Any]]) -> list[str]:
    """
    :param summaries: one per task
    :return: the Markdown of the paper-protocol table and (when a reference column ran) the steps-to-reach table
    """
    labels: list[str] = []
    for summary in summaries:
        labels += [label for label in summary["paper_protocol"]["labels"] if label not in labels]
    lines: list[str] = []
    if labels:
        window = summaries[0]["paper_protocol"]["window"]
        lines += [
            "",
            f"## The paper's protocol: mean return of the training episodes that ended in the last {window} steps",
            "",
            "Mean ± std over seeds, at the task's smallest budget (the step column). Training episodes: what each",
            "algorithm did while learning (POPLIN: MPC), as the paper reports.",
            "",
            "| task | step | " + " | ".join(labels) + " |",
            "|---|---|" + "---|" * len(labels),
        ]
        for summary in summaries:
            paper = summary["paper_protocol"]
            cells = [_mean_cell(paper["labels"].get(label), "values") for label in labels]
            lines.append(f"| {summary['env']} | {paper['step']} | " + " | ".join(cells) + " |")
    reaching = [summary for summary in summaries if "reach" in summary]
    if reaching:
        lines += [
            "",
            "## Steps to reach the reference's final return",
            "",
            "The first step at which the mean curve over seeds reached the reference column's final return (mean over",
            "seeds at the matched step; by the paper's protocol: its training-episode return), then each seed's",
            "(— never). Evaluation steps are the evaluation schedule; the paper's protocol checks every episode end.",
            "",
            "| task | column | evaluation: target | first step | paper's protocol: target | first step |",
            "|---|---|---|---|---|---|",
        ]
        for summary in reaching:
            reach = summary["reach"]
            paper = reach.get("paper_protocol", {})
            paper_target = f"{reach['paper_target']:.1f}" if "paper_target" in reach else "—"
            columns = list(reach["evaluation"]) + [label for label in paper if label not in reach["evaluation"]]
            for label in columns:
                lines.append(
                    f"| {summary['env']} | {label} | {reach['target']:.1f} ({reach['reference']}) | "
                    f"{_reach_cell(reach['evaluation'].get(label))} | {paper_target} | {_reach_cell(paper.get(label))} |"
                )
    return lines


def write_paper_table(summaries: list[dict[str, Any]], budget: str, path: Path) -> None:
    """
    The paper suite's table, laid out as the paper's: one column per task under its paper name, one row per
    algorithm label, then the tasks' env ids and matched steps.

    :param summaries: one per task (with its paper ``name``)
    :param budget: ``"cpu"`` or ``"paper"``
    :param path: the Markdown file to write
    """
    labels = table_labels(summaries)
    lines = [
        f"# POPLIN vs model-free baselines on the POPLIN paper's tasks ({budget} budget)",
        "",
        "Final evaluation return, mean ± std over seeds (each seed: mean over its evaluation episodes), at the",
        "matched step: the last evaluation step every run of the task reached. MPC: planning with the learned",
        "model; policy: the distilled policy network alone. Tasks as the paper names them (sb3_poplin.tasks.paper_suite).",
        "",
        "| | " + " | ".join(summary["name"] for summary in summaries) + " |",
        "|---|" + "---|" * len(summaries),
    ]
    for label in labels:
        cells = [format_cell(summary, label, label_algo(label)) for summary in summaries]
        lines.append(f"| {label} | " + " | ".join(cells) + " |")
    lines.append("| env id | " + " | ".join(f"`{summary['env']}`" for summary in summaries) + " |")
    lines.append("| matched step | " + " | ".join(str(summary["matched_step"]) for summary in summaries) + " |")
    path.write_text("\n".join(lines + protocol_lines(summaries)) + "\n")


def write_table(summaries: list[dict[str, Any]], budget: str, path: Path) -> None:
    """
    :param summaries: one per task
    :param budget: ``"cpu"`` or ``"paper"``
    :param path: the Markdown file to write
    """
    labels = table_labels(summaries)
    lines = [
        f"# POPLIN vs model-free baselines ({budget} budget)",
        "",
        "Final evaluation return, mean ± std over seeds (each seed: mean over its evaluation episodes), at the",
        "matched step: the last evaluation step every run of the task reached. MPC: planning with the learned",
        "model; policy: the distilled policy network alone.",
        "",
        "| task | matched step | " + " | ".join(labels) + " |",
        "|---|---|" + "---|" * len(labels),
    ]
    for summary in summaries:
        cells = [format_cell(summary, label, label_algo(label)) for label in labels]
        lines.append(f"| {summary['env']} | {summary['matched_step']} | " + " | ".join(cells) + " |")
    path.write_text("\n".join(lines + protocol_lines(summaries)) + "\n")


def plot_curves(env: str, curves: list[Curve], budget: str, path: Path) -> None:
    """
    Plot one task's learning curves: mean over seeds with a ± std band, one line per label.

    :param env: the task's title: its gymnasium id (and paper name)
    :param curves: the task's curves
    :param budget: ``"cpu"`` or ``"paper"``
    :param path: the PNG file to write
    """
    import matplotlib

    matplotlib.use("Agg")
    from matplotlib import pyplot as plt

    figure, axis = plt.subplots(figsize=(6.4, 4.4))
    for label in dict.fromkeys(curve.label for curve in curves):
        runs = [curve for curve in curves if curve.label == label]
        length = min(len(curve.timesteps) for curve in runs)
        steps = runs[0].timesteps[:length]
        values = np.stack([curve.returns[:length] for curve in runs])
        mean, std = values.mean(axis=0), values.std(axis=0)
        axis.plot(steps, mean, label=f"{label} ({len(runs)} seeds)", linewidth=2)
        axis.fill_between(steps, mean - std, mean + std, alpha=0.2)
    axis.set_title(f"{env} ({budget} budget)")
    axis.set_xlabel("environment steps")
    axis.set_ylabel("evaluation return (mean ± std over seeds)")
    axis.grid(alpha=0.3)
    axis.legend(fontsize=8)
    figure.tight_layout()
    figure.savefig(path, dpi=120)
    plt.close(figure)


def write_report(
    results: list[JobResult],
    envs: list[str],
    budget: str,
    output: Path,
    paper_names: dict[str, str] | None = None,
    window: int = PAPER_WINDOW,
    reference: str | None = "POPLIN-P (MPC)",
) -> Path:
    """
    Write ``results.md``, ``results.json`` and one ``curves_<task>.png`` per task.

    :param results: every job's result
    :param envs: the tasks, in table order
    :param budget: ``"cpu"`` or ``"paper"``
    :param output: the report folder
    :param paper_names: env id -> the paper's task name, for the paper suite's table (``None``: one row per task)
    :param window: steps of the paper's protocol
    :param reference: the column whose final return the others must reach
    :return: the table's path
    """
    output.mkdir(parents=True, exist_ok=True)
    summaries = []
    for env in envs:
        env_results = [result for result in results if result.job.env == env]
        curves = [curve for result in env_results if result.run_dir is not None for curve in load_curves(result)]
        failed: dict[str, int] = {}
        missing: dict[str, int] = {}
        expected: dict[str, int] = {}
        for result in env_results:
            expected[result.job.column] = expected.get(result.job.column, 0) + 1
            if result.run_dir is None:
                absent = missing if result.missing else failed
                absent[result.job.column] = absent.get(result.job.column, 0) + 1
        finished = [result for result in env_results if result.run_dir is not None]
        training = [episodes for result in finished if (episodes := load_training(result)) is not None]
        budget_step = min((result.job.n_timesteps for result in env_results), default=None)
        summary = summarize(env, curves, failed, expected, training, budget_step, window, reference, missing)
        summary["name"] = (paper_names or {}).get(env, env)
        summaries.append(summary)
        if curves:
            title = env if summary["name"] == env else f"{summary['name']} ({env})"
            plot_curves(title, curves, budget, output / f"curves_{env_name(env)}.png")
    table = output / "results.md"
    if paper_names:
        write_paper_table(summaries, budget, table)
    else:
        write_table(summaries, budget, table)
    runs = [{**asdict(result.job), "run_dir": result.run_dir, "returncode": result.returncode} for result in results]
    suite = "paper" if paper_names else "all"
    report = {"budget": budget, "suite": suite, "reference": reference, "tasks": summaries, "runs": runs}
    (output / "results.json").write_text(json.dumps(report, indent=2))
    return table


# ------------------------------------------------------------------------------------------------- planning
def algo_settings(
    algo: str, env: str, n_timesteps: int, poplin_conf: Path, params: list[str], options: argparse.Namespace
) -> tuple[str | None, list[str]]:
    """
    The hyperparameter file and ``-params`` of one algorithm on one task.

    :param algo: rl-zoo3 algorithm name
    :param env: gymnasium id
    :param n_timesteps: the task's matched budget (not a ``--steps-scale`` run's longer one)
    :param poplin_conf: POPLIN's hyperparameter file for the budget
    :param params: ``--params`` settings for this algorithm (``KEY:VALUE``)
    :param options: the command line

    Random shooting (``rs``) samples ``population_size x cem_iterations`` action sequences in its one round, the
    number of candidates CEM evaluates per step with the same file's settings (the original code's 2500 = 500 x 5),
    unless ``--params`` sets its population.

    A baseline whose random warm-up (``learning_starts``) would take half the matched budget or more, as the zoo's
    MuJoCo settings (5000-10000 steps) do with CPU budgets, starts learning after a tenth of it instead, unless
    ``--params`` sets it or ``--keep-learning-starts`` is given. A run trained longer (``--steps-scale``) takes the
    same warm-up as at the matched budget: its first ``n_timesteps`` steps are the matched run's, so the main table's
    column at the matched step is not a run still in its warm-up (SAC on PETSCheetah with the zoo's 10 000 random
    steps scored -61 at 15 000 steps, and 3497 at 45 000).

    :return: the ``--conf-file`` (``None``: the zoo's own) and the ``-params`` overrides
    """
    is_poplin = algo == "poplin" or algo in VARIANTS
    conf: Path | None = poplin_conf if is_poplin else hyperparams_dir() / f"{algo}.yml"
    entry = read_yaml(conf).get(env) if conf is not None and conf.is_file() else None
    if entry is None and is_poplin:
        raise SystemExit(f"{env} has no entry in {poplin_conf}.")
    if entry is None:
        return None, params  # the zoo's own file
    if algo in VARIANTS and not any(setting.startswith("policy:") for setting in params):
        params = [f"policy:{algo!r}", *params]  # the task's settings, with this variant's own defaults
    if algo == "rs" and not any(setting.startswith("population_size:") for setting in params):
        # as many model rollouts per step as CEM's iterations make (the original: 2500 = 500 x 5)
        population = int(entry.get("population_size", DEFAULT_SETTINGS["population_size"]))
        iterations = int(entry.get("cem_iterations", DEFAULT_SETTINGS["cem_iterations"]))
        params = [*params, f"population_size:{population * iterations}"]
    learning_starts = int(entry.get("learning_starts", 0))
    overridden = any(setting.startswith("learning_starts:") for setting in params)
    if not is_poplin and learning_starts >= n_timesteps / 2 and not overridden:
        if options.keep_learning_starts:
            print(f"warning: {algo} on {env} learns only after {learning_starts} of the {n_timesteps} matched steps")
        else:
            params = [*params, f"learning_starts:{n_timesteps // 10}"]
            print(
                f"note: {algo} on {env}: learning_starts {learning_starts} -> {n_timesteps // 10} "
                f"({n_timesteps} matched steps)"
            )
    return str(conf), params


def evaluation_episodes(env: str, given: int | None, budget: str) -> int:
    """
    The episodes of each evaluation. The rule: an evaluation of a task whose episodes are short (at most
    :data:`SHORT_EPISODE` steps, e.g. Pendulum-v1) averages at least :data:`SHORT_EPISODE_EVALUATIONS` episodes, since
    its return depends on the start state far more than a long episode's (Pendulum-v1: -1 from near upright, about
    -400 from the bottom); a long task's evaluation takes 3 episodes (``--budget cpu``) or 5 (``paper``).

    :param env: gymnasium id
    :param given: ``--eval-episodes`` (``None``: by the rule); fewer than the rule asks gets a warning
    :param budget: ``"cpu"`` or ``"paper"``
    :return: episodes per evaluation
    """
    episode = gym.spec(env).max_episode_steps if env in gym.registry else None
    short = episode is not None and episode <= SHORT_EPISODE
    default = SHORT_EPISODE_EVALUATIONS if short else (3 if budget == "cpu" else 5)
    if given is None:
        return default
    if short and given < SHORT_EPISODE_EVALUATIONS:
        print(
            f"warning: {env}'s episodes are {episode} steps: {given} evaluation episodes rank nothing (a return depends "
            f"on the start state); use --eval-episodes {SHORT_EPISODE_EVALUATIONS} or more"
        )
    return given


def plan_jobs(options: argparse.Namespace) -> list[Job]:
    """
    :param options: the command line
    :return: one job per algorithm x task x seed, with matched budgets and evaluation settings
    """
    folder = hyperparams_dir()
    poplin_conf = folder / ("poplin_cpu.yml" if options.budget == "cpu" else "poplin.yml")
    poplin_config = read_yaml(poplin_conf)
    params: dict[str, list[str]] = {}
    for item in options.params:
        algo, _, setting = item.partition(":")
        if algo not in options.algos or ":" not in setting:
            raise SystemExit(f"--params takes ALGO:KEY:VALUE with ALGO among {options.algos}, got {item!r}")
        params.setdefault(algo, []).append(setting)
    scales: dict[str, float] = {}
    for item in options.steps_scale:
        algo, _, factor = item.partition(":")
        try:
            scales[algo] = float(factor)
        except ValueError:
            scales[algo] = -1.0
        if algo not in options.algos or scales[algo] <= 0:
            raise SystemExit(f"--steps-scale takes ALGO:FACTOR with ALGO among {options.algos} and FACTOR > 0, got {item!r}")
    jobs = []
    log_folder = os.path.abspath(options.log_folder or f"logs/compare-{options.budget}")
    if options.suite == "paper":
        options.paper_names = paper_suite_envs(options.envs)
        options.envs = list(options.paper_names)
    else:
        options.paper_names = {}
        options.envs = options.envs or list(poplin_config)
    for env in options.envs:
        if options.n_timesteps is not None:
            n_timesteps = options.n_timesteps
        elif env in poplin_config:
            n_timesteps = int(poplin_config[env]["n_timesteps"])
        else:
            raise SystemExit(f"{env} has no entry in {poplin_conf}: pass -n to set its budget.")
        eval_freq = options.eval_freq or max(n_timesteps // options.n_evals, 1)
        eval_episodes = evaluation_episodes(env, options.eval_episodes, options.budget)
        for algo in options.algos:
            algo_steps = round(n_timesteps * scales.get(algo, 1.0))
            conf, algo_params = algo_settings(algo, env, n_timesteps, poplin_conf, params.get(algo, []), options)
            for seed in options.seeds:
                jobs.append(
                    Job(
                        algo=algo,
                        env=env,
                        seed=seed,
                        n_timesteps=algo_steps,
                        eval_freq=eval_freq,
                        eval_episodes=eval_episodes,
                        conf_file=conf,
                        params=algo_params,
                        log_folder=log_folder,
                        python=options.python,
                        policy_eval_freq=options.policy_eval_freq if algo == "poplin" or algo in VARIANTS else None,
                    )
                )
    return jobs


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    """
    :param argv: the arguments (``None``: ``sys.argv[1:]``)
    :return: the options
    """
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
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
    options = parser.parse_args(argv)
    if options.eval_episodes is not None and options.eval_episodes < 2:
        parser.error("--eval-episodes must be >= 2 (rl-zoo3's all_plots needs it)")
    if options.jobs < 1 or options.n_evals < 1 or options.paper_window < 1:
        parser.error("--jobs, --n-evals and --paper-window must be >= 1")
    if options.policy_eval_freq is not None and options.policy_eval_freq < 1:
        parser.error("--policy-eval-freq must be >= 1")
    return options


def main(argv: list[str] | None = None) -> int:
    """
    Plan, run and report a comparison.

    :param argv: the arguments (``None``: ``sys.argv[1:]``)
    :return: the exit code: 1 when a run failed or is missing
    """
    options = parse_args(argv)
    jobs = plan_jobs(options)
    print(f"{len(jobs)} runs ({len(options.algos)} algorithms x {len(options.envs)} tasks x {len(options.seeds)} seeds)")
    if options.report_only:
        results = []
        for job in jobs:
            run_dir = find_run(job)
            results.append(JobResult(job, 0 if run_dir else 1, run_dir, reused=run_dir is not None, missing=not run_dir))
    elif options.ray_address:
        results = run_ray(jobs, options.ray_address, options.jobs, options.force)
    else:
        results = run_local(jobs, options.jobs, options.force)
    output = Path(options.output or os.path.join(jobs[0].log_folder if jobs else ".", "report"))
    table = write_report(
        results, list(options.envs), options.budget, output, options.paper_names, options.paper_window, options.reference
    )
    print(table.read_text())
    print(f"Report: {output}")
    n_missing = sum(result.run_dir is None and result.missing for result in results)
    n_failed = sum(result.run_dir is None and not result.missing for result in results)
    if n_failed:
        print(f"{n_failed} of {len(results)} runs failed (see {jobs[0].log_folder}/compare_logs)")
    if n_missing:
        print(f"{n_missing} of {len(results)} runs are missing: --report-only reports complete runs, run without it")
    return 1 if n_failed or n_missing else 0


if __name__ == "__main__":
    sys.exit(main())
