"""
The comparison's runs: the options (:class:`CompareOptions`), one :class:`Job` per algorithm x task x seed with its
budget, hyperparameter file and ``-params``, the result record of a run (:class:`JobResult`), and the runs that already
exist in the log folder (complete ones to reuse, interrupted ones to continue).
"""

from __future__ import annotations

import os
import sys
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import gymnasium as gym
import yaml

from sb3_poplin.experiments.checkpoints import CHECKPOINT_FOLDER, latest_checkpoint
from sb3_poplin.experiments.presets import PACKAGED_ALGOS, config_path, load_config
from sb3_poplin.tasks.paper_suite import PAPER_TASKS
from sb3_poplin.variants import DEFAULT_SETTINGS
from sb3_poplin.variants import VARIANTS as VARIANT_TABLE

# POPLIN variants run as the zoo algorithm "poplin" with ``policy`` set; "poplin" alone is the file's variant
VARIANTS = tuple(VARIANT_TABLE)
ALGOS = ("poplin", *VARIANTS, *(algo for algo in PACKAGED_ALGOS if algo != "poplin"))
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


@dataclass
class CompareOptions:
    """
    What a comparison runs and reports (the command line's options, :func:`sb3_poplin.experiments.compare.parse_args`).

    :param algos: rl-zoo3 algorithm names and POPLIN variants
    :param envs: gymnasium ids; ``None``: every task of the budget's POPLIN file (with ``suite="paper"``: the paper's
        13 tasks; paper names are taken too)
    :param suite: ``"all"`` or ``"paper"``
    :param seeds: the seeds of every algorithm x task
    :param budget: ``"cpu"`` (``poplin_cpu.yml``) or ``"paper"`` (``poplin.yml``)
    :param n_timesteps: training steps of every run; ``None``: the budget file's per task
    :param n_evals: evaluations per run (sets ``eval_freq`` when that is ``None``)
    :param eval_freq: evaluation period in steps
    :param policy_eval_freq: period of POPLIN-A/P's policy-control evaluation (``None``: ``eval_freq``)
    :param eval_episodes: episodes per evaluation (``None``: :func:`evaluation_episodes`' rule)
    :param jobs: parallel runs
    :param ray_address: run as Ray tasks there (``None``: a local pool)
    :param params: ``ALGO:KEY:VALUE`` overrides
    :param steps_scale: ``ALGO:FACTOR``: train ALGO FACTOR times the task's budget
    :param paper_window: the paper's protocol: training episodes of the last N steps
    :param reference: the column the steps-to-reach table measures against
    :param protocol_steps: more steps to report the paper's protocol at (empty: the task's budget only)
    :param log_folder: rl-zoo3's log folder (``None``: ``logs/compare-<budget>``)
    :param output: the report folder (``None``: ``<log folder>/report``)
    :param python: the runs' interpreter
    :param keep_learning_starts: keep the baselines' long random warm-up
    :param force: train again even where a complete run exists
    :param report_only: train nothing, report the complete runs
    :param include_unfinished: with ``report_only``, also report the interrupted runs as far as they got
    """

    algos: list[str] = field(default_factory=lambda: list(ALGOS))
    envs: list[str] | None = None
    suite: str = "all"
    seeds: list[int] = field(default_factory=lambda: [0, 1, 2])
    budget: str = "cpu"
    n_timesteps: int | None = None
    n_evals: int = 10
    eval_freq: int | None = None
    policy_eval_freq: int | None = None
    eval_episodes: int | None = None
    jobs: int = 2
    ray_address: str | None = None
    params: list[str] = field(default_factory=list)
    steps_scale: list[str] = field(default_factory=list)
    paper_window: int = PAPER_WINDOW
    reference: str = "POPLIN-P (MPC)"
    protocol_steps: list[int] = field(default_factory=list)
    log_folder: str | None = None
    output: str | None = None
    python: str = sys.executable
    keep_learning_starts: bool = False
    force: bool = False
    report_only: bool = False
    include_unfinished: bool = False

    def poplin_conf(self) -> Path:
        """:return: POPLIN's hyperparameter file of the budget"""
        path = config_path("poplin", self.budget)
        assert path is not None
        return path

    @property
    def paper_names(self) -> dict[str, str]:
        """The paper's name of each task (``suite="paper"``; empty otherwise), by gymnasium id."""
        return paper_suite_envs(self.envs) if self.suite == "paper" else {}

    def tasks(self) -> list[str]:
        """:return: the gymnasium ids compared, in order"""
        if self.suite == "paper":
            return list(self.paper_names)
        return list(self.envs) if self.envs else list(load_config(self.poplin_conf()))


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
        entry = load_config(self.conf_file).get(self.env, {}) if self.conf_file else {}
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
    :param unfinished: ``run_dir`` is an interrupted run, reported as far as it got (``--include-unfinished``)
    """

    job: Job
    returncode: int
    run_dir: str | None = None
    reused: bool = False
    resumed: str | None = None
    output_tail: str = ""
    files: dict[str, bytes] = field(default_factory=dict)
    missing: bool = False
    unfinished: bool = False


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
        the one with the most training episodes (copies of runs without their checkpoints), else the newest one;
        ``None`` when there is none
    """
    interrupted = [(mtime, run) for mtime, run, done in job_runs(job) if not done]
    if not interrupted:
        return None

    def progress(item: tuple[float, Path]) -> tuple[int, int, float]:
        checkpoint = latest_checkpoint(item[1])
        episodes = sum(max(0, len(path.read_text().splitlines()) - 2) for path in item[1].glob("*.monitor.csv"))
        return (int(checkpoint.name.split("-", 1)[1]) if checkpoint is not None else -1, episodes, item[0])

    return str(max(interrupted, key=progress)[1].relative_to(job.log_folder))


def algo_settings(
    algo: str, env: str, n_timesteps: int, poplin_conf: Path, params: list[str], keep_learning_starts: bool = False
) -> tuple[str | None, list[str]]:
    """
    The hyperparameter file and ``-params`` of one algorithm on one task.

    :param algo: rl-zoo3 algorithm name
    :param env: gymnasium id
    :param n_timesteps: the task's matched budget (not a ``--steps-scale`` run's longer one)
    :param poplin_conf: POPLIN's hyperparameter file for the budget
    :param params: ``--params`` settings for this algorithm (``KEY:VALUE``)
    :param keep_learning_starts: keep a baseline's random warm-up even when it takes half the budget or more

    Random shooting (``rs``) samples ``population_size x cem_iterations`` action sequences in its one round, the
    number of candidates CEM evaluates per step with the same file's settings (the original code's 2500 = 500 x 5),
    unless ``--params`` sets its population.

    A baseline whose random warm-up (``learning_starts``) would take half the matched budget or more, as the zoo's
    MuJoCo settings (5000-10000 steps) do with CPU budgets, starts learning after a tenth of it instead, unless
    ``--params`` sets it or ``--keep-learning-starts`` is given. A run trained longer (``--steps-scale``) takes the
    same warm-up as at the matched budget: its first ``n_timesteps`` steps are the matched run's, so the main table's
    column at the matched step is not a run still in its warm-up.

    :return: the ``--conf-file`` (``None``: the zoo's own) and the ``-params`` overrides
    """
    is_poplin = algo == "poplin" or algo in VARIANTS
    conf = poplin_conf if is_poplin else config_path(algo)
    entry = load_config(conf).get(env) if conf is not None else None
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
        if keep_learning_starts:
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


def plan_jobs(options: CompareOptions) -> list[Job]:
    """
    :param options: what to compare
    :return: one job per algorithm x task x seed, with matched budgets and evaluation settings
    """
    poplin_conf = options.poplin_conf()
    poplin_config = load_config(poplin_conf)
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
    for env in options.tasks():
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
            conf, algo_params = algo_settings(
                algo, env, n_timesteps, poplin_conf, params.get(algo, []), options.keep_learning_starts
            )
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
