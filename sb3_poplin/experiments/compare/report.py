"""
The comparison's report: evaluation curves and training episodes of the runs, summaries per task and algorithm
(final and matched-step returns, the paper's protocol, steps to reach the reference), ``results.md``,
``results.json`` and the learning-curve figures.
"""

from __future__ import annotations

import json
from dataclasses import asdict, dataclass, field
from pathlib import Path
from collections.abc import Callable
from typing import Any

import numpy as np
import yaml

from sb3_poplin.experiments.compare.jobs import PAPER_WINDOW, JobResult, env_name
from sb3_poplin.variants import POLICY_VARIANTS

RUN_TIME_GAP = 3.0  # an episode longer than this many times its run's median held an interruption (run time)


@dataclass
class Curve:
    """
    Evaluation results of one run under one label.

    :param label: row label, e.g. ``"SAC"`` or ``"POPLIN-P (policy)"``
    :param seed: the run's seed
    :param timesteps: evaluation steps
    :param returns: mean evaluation return at each of them
    :param unfinished: the run was interrupted (``--include-unfinished``)
    """

    label: str
    seed: int
    timesteps: np.ndarray
    returns: np.ndarray
    unfinished: bool = False


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
            returns = results.reshape(len(timesteps), -1).mean(axis=1)
            curves.append(Curve(label, job.seed, timesteps, returns, result.unfinished))
    return curves


@dataclass
class TrainingEpisodes:
    """
    The training episodes of one run (its monitor files), for the paper's protocol.

    :param label: the algorithm's label, e.g. ``"POPLIN-P"`` or ``"SAC"``
    :param seed: the run's seed
    :param end_steps: the environment step at which each episode ended
    :param returns: each episode's return
    :param n_timesteps: the steps the run trained (``None``: unknown)
    :param end_times: the wall time at which each episode ended, in seconds since the run's monitor started (its
        ``t`` column; a resumed run's monitor keeps its start, so the time it was stopped is inside one episode)
    """

    label: str
    seed: int
    end_steps: np.ndarray
    returns: np.ndarray
    n_timesteps: int | None = None
    end_times: np.ndarray | None = None

    def run_time(self, gap: float = RUN_TIME_GAP) -> tuple[float, int]:
        """
        The time the run computed, which for an interrupted run is less than the span of its monitor.

        :param gap: an episode that took more than ``gap`` times the run's median episode held an interruption
        :return: the sum of the episodes' durations (the evaluations and model fits between them included), each
            interrupted episode counted at the median; and the number of such episodes
        """
        if self.end_times is None or len(self.end_times) == 0:
            return float("nan"), 0
        durations = np.diff(np.concatenate([[0.0], np.sort(np.asarray(self.end_times, dtype=float))]))
        median = float(np.median(durations))
        interrupted = durations > gap * median
        return float(durations[~interrupted].sum() + median * interrupted.sum()), int(interrupted.sum())

    def window_mean(self, step: int, window: int) -> float:
        """
        :param step: environment step
        :param window: steps
        :return: the mean return of the episodes that ended in ``(step - window, step]`` (``nan`` when none did, or
            when ``step`` is past the run's ``n_timesteps``: a run that stopped has no value there)
        """
        if self.n_timesteps is not None and step > self.n_timesteps:
            return float("nan")
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
    returns, lengths, times = (np.asarray(column, dtype=float) for column in zip(*rows, strict=True))
    end_steps = np.cumsum(lengths).astype(int)
    # an unfinished run has trained as far as its last episode's end, not its budget
    trained = int(end_steps[-1]) if result.unfinished else job.n_timesteps
    return TrainingEpisodes(job.column.upper(), job.seed, end_steps, returns, trained, times)


def first_step_reaching(steps: np.ndarray, values: np.ndarray, target: float) -> int | None:
    """
    :param steps: increasing environment steps
    :param values: a return at each of them (``nan``: not defined yet)
    :param target: the return to reach
    :return: the first step whose value is at least ``target`` (``None``: never)
    """
    reached = np.flatnonzero(np.nan_to_num(values, nan=-np.inf) >= target)
    return int(steps[reached[0]]) if len(reached) else None


@dataclass
class SeedValues:
    """
    One column's value on each seed.

    :param seeds: the seeds
    :param values: one value a seed, in the same order
    """

    seeds: list[int] = field(default_factory=list)
    values: list[float] = field(default_factory=list)

    def add(self, seed: int, value: float) -> None:
        self.seeds.append(seed)
        self.values.append(value)

    @property
    def mean(self) -> float:
        return float(np.mean(self.values))

    @property
    def std(self) -> float:
        """The population standard deviation over seeds (``ddof=0``)."""
        return float(np.std(self.values))

    def to_json(self, key: str) -> dict[str, Any]:
        """:param key: the name of the values in ``results.json`` (``"final"`` or ``"values"``)"""
        return {"seeds": self.seeds, key: self.values, "mean": self.mean, "std": self.std}


@dataclass
class ReachEntry:
    """
    When one column first reached a target return.

    :param step: the first step of the mean curve over seeds at or above the target (``None``: never)
    :param per_seed: seed (as text) -> its curve's first step at or above the target (``None``: never)
    :param last_step: the last step the mean curve is defined at (the shortest seed's last)
    :param short: seed (as text) -> the last step of its curve, for the seeds whose curve ends before the longest
        one's (interrupted runs): their ``None`` in ``per_seed`` means "not by then", not "never"
    """

    step: int | None
    per_seed: dict[str, int | None]
    last_step: int
    short: dict[str, int] = field(default_factory=dict)

    def to_json(self) -> dict[str, Any]:
        entry = asdict(self)
        if not self.short:
            del entry["short"]
        return entry


@dataclass
class Reach:
    """
    The steps at which the columns reached the reference column's final return.

    :param reference: the reference column's label
    :param target: its mean final evaluation return
    :param evaluation: label -> when its evaluation curve reached ``target``
    :param paper_target: the reference's return by the paper's protocol (``None``: it has no training episodes)
    :param paper_protocol: algorithm label -> when its training-episode curve reached ``paper_target``
    """

    reference: str
    target: float
    evaluation: dict[str, ReachEntry] = field(default_factory=dict)
    paper_target: float | None = None
    paper_protocol: dict[str, ReachEntry] = field(default_factory=dict)

    def to_json(self) -> dict[str, Any]:
        entry: dict[str, Any] = {
            "reference": self.reference,
            "target": self.target,
            "evaluation": {label: reach.to_json() for label, reach in self.evaluation.items()},
        }
        if self.paper_target is not None:
            entry["paper_target"] = self.paper_target
            entry["paper_protocol"] = {label: reach.to_json() for label, reach in self.paper_protocol.items()}
        return entry


@dataclass
class ProtocolSummary:
    """
    The paper's protocol on one task: each algorithm's mean return of the training episodes that ended in the last
    ``window`` steps before ``step``.

    :param step: the protocol's step (``None``: not computed)
    :param window: steps
    :param labels: algorithm label -> its value on each seed
    """

    step: int | None
    window: int
    labels: dict[str, SeedValues] = field(default_factory=dict)

    def to_json(self) -> dict[str, Any]:
        labels = {label: values.to_json("values") for label, values in self.labels.items()}
        return {"step": self.step, "window": self.window, "labels": labels}


@dataclass
class TaskSummary:
    """
    One task's results: the final evaluation returns at the matched step, the paper's protocol, the steps to reach.

    :param env: gymnasium id
    :param matched_step: the last evaluation step every run of the task reached
    :param labels: column label -> each seed's evaluation return at ``matched_step``
    :param failed: algorithm -> runs that failed
    :param expected: algorithm -> runs planned
    :param missing: algorithm -> runs not found and not started (``--report-only``)
    :param paper_protocol: the paper's protocol
    :param unfinished: column label -> its seeds that are interrupted runs, reported as far as they got
        (``--include-unfinished``)
    :param interrupted: algorithm -> its interrupted runs (``--include-unfinished``), with a value at
        ``matched_step`` or not (:meth:`short`)
    :param reach: the steps to reach the reference's final return (``None``: no reference column ran)
    :param name: the task's name in the tables (the paper's, in the paper suite)
    :param protocol_at: the paper's protocol at more steps (``--protocol-steps``), in order
    """

    env: str
    matched_step: int
    labels: dict[str, SeedValues]
    failed: dict[str, int]
    expected: dict[str, int]
    missing: dict[str, int]
    paper_protocol: ProtocolSummary
    reach: Reach | None = None
    name: str = ""
    protocol_at: list[ProtocolSummary] = field(default_factory=list)
    unfinished: dict[str, int] = field(default_factory=dict)
    interrupted: dict[str, int] = field(default_factory=dict)

    def __post_init__(self) -> None:
        self.name = self.name or self.env

    def short(self, label: str) -> int:
        """:return: the column's interrupted runs that have no value at the matched step (not there yet)"""
        return self.interrupted.get(label_algo(label), 0) - self.unfinished.get(label, 0)

    def to_json(self) -> dict[str, Any]:
        """The task's entry of ``results.json``."""
        entry: dict[str, Any] = {
            "env": self.env,
            "matched_step": self.matched_step,
            "labels": {label: values.to_json("final") for label, values in self.labels.items()},
            "failed": self.failed,
            "expected": self.expected,
            "missing": self.missing,
            "paper_protocol": self.paper_protocol.to_json(),
        }
        if self.reach is not None:
            entry["reach"] = self.reach.to_json()
        entry["name"] = self.name
        if self.protocol_at:
            entry["paper_protocol_at"] = [protocol.to_json() for protocol in self.protocol_at]
        if self.unfinished:
            entry["unfinished"] = self.unfinished
        if self.interrupted:
            entry["interrupted"] = self.interrupted
            entry["short"] = {label: self.short(label) for label in self.labels if self.short(label)}
        return entry


def reach_entry(steps: np.ndarray, per_seed: list[np.ndarray], seeds: list[int], target: float) -> ReachEntry:
    """
    :param steps: the steps shared by the seeds' curves
    :param per_seed: each seed's return at those steps
    :param seeds: the seeds
    :param target: the return to reach
    :return: the first step of the mean curve (over seeds) and of each seed's curve that reached ``target``
    """
    mean = np.mean(np.stack(per_seed), axis=0)
    defined = np.flatnonzero(np.isfinite(mean))  # the mean is undefined past the end of an unfinished seed
    ends = {}
    for seed, values in zip(seeds, per_seed, strict=True):
        finite = np.flatnonzero(np.isfinite(values))
        ends[str(seed)] = int(steps[finite[-1]]) if len(finite) else int(steps[0])
    longest = max(ends.values())
    return ReachEntry(
        first_step_reaching(steps, mean, target),
        {str(seed): first_step_reaching(steps, values, target) for seed, values in zip(seeds, per_seed, strict=True)},
        int(steps[defined[-1]] if len(defined) else steps[-1]),
        {seed: end for seed, end in ends.items() if end < longest},
    )


def value_at(curve: Curve, step: int) -> float:
    """
    :param curve: evaluation curve
    :param step: environment step
    :return: the curve's return at its last evaluation at or before ``step``
    """
    index = int(np.searchsorted(curve.timesteps, step, side="right")) - 1
    return float(curve.returns[max(index, 0)])


def paper_protocol(training: list[TrainingEpisodes], step: int | None, window: int) -> ProtocolSummary:
    """
    :param training: the task's training episodes (one per run)
    :param step: the protocol's step (``None``: an empty summary)
    :param window: steps
    :return: each algorithm's mean return of the training episodes that ended in ``(step - window, step]``, per seed
        (a run with no episode there is left out)
    """
    protocol = ProtocolSummary(step, window)
    if step is not None:
        for episodes in training:
            value = episodes.window_mean(step, window)
            if not np.isnan(value):
                protocol.labels.setdefault(episodes.label, SeedValues()).add(episodes.seed, value)
    return protocol


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
    protocol_steps: list[int] | None = None,
    interrupted: dict[str, int] | None = None,
) -> TaskSummary:
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
    :param protocol_steps: more steps to apply the paper's protocol at (a learning curve by the paper's measure)
    :param interrupted: algorithm -> its interrupted runs (``--include-unfinished``)
    """
    # the last step every complete run reached (only unfinished ones: every run); an unfinished run that did not reach
    # it, or a curve with no evaluation by then, has no value there
    complete = [curve for curve in curves if not curve.unfinished] or curves
    matched = int(min(curve.timesteps[-1] for curve in complete)) if curves else 0
    labels: dict[str, SeedValues] = {}
    unfinished: dict[str, int] = {}
    for curve in curves:
        if curve.timesteps[0] > matched or curve.timesteps[-1] < matched:
            continue
        labels.setdefault(curve.label, SeedValues()).add(curve.seed, value_at(curve, matched))
        if curve.unfinished:
            unfinished[curve.label] = unfinished.get(curve.label, 0) + 1
    training = training or []
    protocol = paper_protocol(training, budget_step, window)
    summary = TaskSummary(
        env,
        matched,
        labels,
        failed,
        expected,
        dict(missing or {}),
        protocol,
        unfinished=unfinished,
        interrupted=dict(interrupted or {}),
    )
    summary.protocol_at = [paper_protocol(training, step, window) for step in protocol_steps or []]
    if reference is None or reference not in labels:
        return summary
    reach = Reach(reference, labels[reference].mean)
    for label in labels:
        runs = [curve for curve in curves if curve.label == label and curve.seed in labels[label].seeds]
        length = min(len(curve.timesteps) for curve in runs)
        values = [curve.returns[:length] for curve in runs]
        reach.evaluation[label] = reach_entry(runs[0].timesteps[:length], values, [c.seed for c in runs], reach.target)
    paper_reference = protocol.labels.get(label_algo(reference).upper())
    if paper_reference is not None:
        reach.paper_target = paper_reference.mean
        for label in dict.fromkeys(episodes.label for episodes in training):
            trained = [episodes for episodes in training if episodes.label == label]
            steps = np.unique(np.concatenate([episodes.end_steps for episodes in trained]))
            values = [np.array([episodes.window_mean(int(step), window) for step in steps]) for episodes in trained]
            seeds = [episodes.seed for episodes in trained]
            reach.paper_protocol[label] = reach_entry(steps, values, seeds, reach.paper_target)
    summary.reach = reach
    return summary


def format_cell(summary: TaskSummary, label: str, algo: str) -> str:
    """
    :param summary: a task's summary
    :param label: column label
    :param algo: the label's algorithm
    :return: the table cell: mean ± std over seeds, the number of seeds, of failed runs, of missing ones (not run
        yet: ``--report-only``), of unfinished ones among the seeds and of unfinished ones that have not reached the
        matched step yet (``--include-unfinished``)
    """
    entry = summary.labels.get(label)
    absent = {"failed": summary.failed.get(algo, 0), "missing": summary.missing.get(algo, 0)}
    if summary.unfinished.get(label, 0):
        absent["unfinished"] = summary.unfinished[label]
    if summary.short(label):
        absent[f"not at {summary.matched_step} yet"] = summary.short(label)
    note = "".join(f", {count} {kind}" for kind, count in absent.items() if count)
    if entry is None:
        expected = summary.expected.get(algo, 0)
        return ", ".join(f"{kind} ({count}/{expected})" for kind, count in absent.items() if count) or "—"
    return f"{_spread(entry)} ({_seeds(len(entry.values))}{note})"


def label_algo(label: str) -> str:
    """
    :param label: column label, e.g. ``"POPLIN-P (MPC)"`` or ``"SAC"``
    :return: its algorithm (a POPLIN variant for POPLIN's columns), as ``Job.column`` names it
    """
    return label.removesuffix(" (MPC)").removesuffix(" (policy)").lower()


def table_labels(summaries: list[TaskSummary]) -> list[str]:
    """
    :param summaries: one per task
    :return: every algorithm label of the report, in order of appearance (an algorithm whose every run failed too)
    """
    labels: list[str] = []
    for summary in summaries:
        labels += [label for label in summary.labels if label not in labels]
    for summary in summaries:
        for algo in [*summary.failed, *summary.missing]:
            if not any(label_algo(label) == algo for label in labels):
                labels.append(algo.upper())
    return labels


def _spread(entry: SeedValues) -> str:
    """The mean, and the std over seeds where there are several (one seed has no spread to show)."""
    return f"{entry.mean:.1f}" if len(entry.values) == 1 else f"{entry.mean:.1f} ± {entry.std:.1f}"


def _mean_cell(entry: SeedValues | None) -> str:
    if entry is None:
        return "—"
    return f"{_spread(entry)} ({_seeds(len(entry.values))})"


def _seeds_cell(entry: SeedValues | None) -> str:
    if entry is None:
        return "—"
    values = ", ".join(f"s{seed}: {value:.0f}" for seed, value in zip(entry.seeds, entry.values, strict=True))
    return f"{_spread(entry)} ({values})"


def _reach_cell(entry: ReachEntry | None) -> str:
    if entry is None:
        return "—"

    def seed_cell(seed: str, step: int | None) -> str:
        if step is not None:
            return str(step)
        return f"not by {entry.short[seed]}" if seed in entry.short else "—"

    per_seed = ", ".join(f"s{seed}: {seed_cell(seed, step)}" for seed, step in entry.per_seed.items())
    first = f"not by {entry.last_step}" if entry.step is None else str(entry.step)
    return f"{first} ({per_seed})"


def _protocol_table(
    title: str, intro: list[str], rows: list[tuple[str, ProtocolSummary]], cell: Callable[[SeedValues | None], str]
) -> list[str]:
    """The Markdown of one paper-protocol table: a row per (task, protocol), a column per algorithm label."""
    labels: list[str] = []
    for _, protocol in rows:
        labels += [label for label in protocol.labels if label not in labels]
    header = ["| task | step | " + " | ".join(labels) + " |", "|---|---|" + "---|" * len(labels)]
    lines = ["", f"## {title}", "", *intro, "", *header]
    for env, protocol in rows:
        cells = [cell(protocol.labels.get(label)) for label in labels]
        lines.append(f"| {env} | {protocol.step} | " + " | ".join(cells) + " |")
    return lines


def protocol_lines(summaries: list[TaskSummary]) -> list[str]:
    """
    :param summaries: one per task
    :return: the Markdown of the paper-protocol table and (when a reference column ran) the steps-to-reach table
    """
    lines: list[str] = []
    at_budget = [(summary.env, summary.paper_protocol) for summary in summaries]
    if any(protocol.labels for _, protocol in at_budget):
        window = summaries[0].paper_protocol.window
        title = f"The paper's protocol: mean return of the training episodes that ended in the last {window} steps"
        intro = [
            "Mean ± std over seeds, at the task's smallest budget (the step column). Training episodes: what each",
            "algorithm did while learning (POPLIN: MPC), as the paper reports.",
        ]
        lines += _protocol_table(title, intro, at_budget, _mean_cell)
    along = [(summary.env, protocol) for summary in summaries for protocol in summary.protocol_at]
    if along:
        intro = ["The same measure at each step (`--protocol-steps`): mean ± std over seeds, then each seed's value."]
        lines += _protocol_table("The paper's protocol along training", intro, along, _seeds_cell)
    reaching = [(summary, summary.reach) for summary in summaries if summary.reach is not None]
    if reaching:
        lines += [
            "",
            "## Steps to reach the reference's final return",
            "",
            "The first step at which the mean curve over seeds reached the reference column's final return (mean over",
            "seeds at the matched step; by the paper's protocol: its training-episode return), then each seed's",
            '(— never; "not by N": an interrupted run that stopped at N). Evaluation steps are the evaluation',
            "schedule; the paper's protocol checks every episode end.",
            "",
            "| task | column | evaluation: target | first step | paper's protocol: target | first step |",
            "|---|---|---|---|---|---|",
        ]
        for summary, reach in reaching:
            paper_target = "—" if reach.paper_target is None else f"{reach.paper_target:.1f}"
            columns = list(reach.evaluation) + [label for label in reach.paper_protocol if label not in reach.evaluation]
            for label in columns:
                lines.append(
                    f"| {summary.env} | {label} | {reach.target:.1f} ({reach.reference}) | "
                    f"{_reach_cell(reach.evaluation.get(label))} | {paper_target} | "
                    f"{_reach_cell(reach.paper_protocol.get(label))} |"
                )
    return lines


def write_paper_table(summaries: list[TaskSummary], budget: str, path: Path) -> None:
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
        "| | " + " | ".join(summary.name for summary in summaries) + " |",
        "|---|" + "---|" * len(summaries),
    ]
    for label in labels:
        cells = [format_cell(summary, label, label_algo(label)) for summary in summaries]
        lines.append(f"| {label} | " + " | ".join(cells) + " |")
    lines.append("| env id | " + " | ".join(f"`{summary.env}`" for summary in summaries) + " |")
    lines.append("| matched step | " + " | ".join(str(summary.matched_step) for summary in summaries) + " |")
    path.write_text("\n".join(lines + protocol_lines(summaries)) + "\n")


def write_table(summaries: list[TaskSummary], budget: str, path: Path) -> None:
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
        lines.append(f"| {summary.env} | {summary.matched_step} | " + " | ".join(cells) + " |")
    path.write_text("\n".join(lines + protocol_lines(summaries)) + "\n")


def run_time_lines(timed: list[tuple[JobResult, TrainingEpisodes]]) -> list[str]:
    """:return: the Markdown of the run-time table: each run's :meth:`TrainingEpisodes.run_time`, and their sum"""
    lines = [
        "",
        "## Run time",
        "",
        "Each run's computing time from its monitor (the wall time at which each training episode ended): the sum of",
        f"its episodes' durations, evaluations and model fits included. An episode that took more than {RUN_TIME_GAP:g} times",
        "its run's median held an interruption (the time the run was stopped) and counts at the median. A run",
        "trains on one core; its span is the monitor's last time, interruptions included. Work an interruption lost",
        "(done after the run's last checkpoint, then redone) is not in either.",
        "",
        "| task | column | seed | episodes | run time (h) | interrupted episodes | span (h) |",
        "|---|---|---|---|---|---|---|",
    ]
    total = 0.0
    for result, episodes in timed:
        seconds, interrupted = episodes.run_time()
        total += seconds
        span = float(np.max(episodes.end_times)) if episodes.end_times is not None else float("nan")
        lines.append(
            f"| {result.job.env} | {result.job.column.upper()} | {result.job.seed} | {len(episodes.returns)} | "
            f"{seconds / 3600:.2f} | {interrupted} | {span / 3600:.2f} |"
        )
    lines += ["", f"All {len(timed)} runs: {total / 3600:.2f} hours of run time."]
    return lines


def _seeds(count: int) -> str:
    return f"{count} seed{'' if count == 1 else 's'}"


def _new_figure() -> tuple[Any, Any]:
    """A figure and its axes, drawn off screen (matplotlib is imported only when a report draws)."""
    import matplotlib

    matplotlib.use("Agg")
    from matplotlib import pyplot as plt

    return plt.subplots(figsize=(6.4, 4.4))


def _save_figure(figure: Any, axis: Any, title: str, ylabel: str, path: Path) -> None:
    """Title, axes labels, grid and legend of a learning-curve figure; write it to ``path`` and close it."""
    from matplotlib import pyplot as plt

    axis.set_title(title)
    axis.set_xlabel("environment steps")
    axis.set_ylabel(ylabel)
    axis.grid(alpha=0.3)
    axis.legend(fontsize=8)
    figure.tight_layout()
    figure.savefig(path, dpi=120)
    plt.close(figure)


def plot_curves(env: str, curves: list[Curve], budget: str, path: Path) -> None:
    """
    Plot one task's learning curves: mean over seeds with a ± std band, one line per label.

    :param env: the task's title: its gymnasium id (and paper name)
    :param curves: the task's curves
    :param budget: ``"cpu"`` or ``"paper"``
    :param path: the PNG file to write
    """
    figure, axis = _new_figure()
    for label in dict.fromkeys(curve.label for curve in curves):
        runs = [curve for curve in curves if curve.label == label]
        length = min(len(curve.timesteps) for curve in runs)
        steps = runs[0].timesteps[:length]
        values = np.stack([curve.returns[:length] for curve in runs])
        mean, std = values.mean(axis=0), values.std(axis=0)
        axis.plot(steps, mean, label=f"{label} ({_seeds(len(runs))})", linewidth=2)
        axis.fill_between(steps, mean - std, mean + std, alpha=0.2)
    _save_figure(figure, axis, f"{env} ({budget} budget)", "evaluation return (mean ± std over seeds)", path)


def training_curve(runs: list[TrainingEpisodes], steps: np.ndarray, window: int) -> np.ndarray:
    """
    :param runs: one label's training episodes, one per seed
    :param steps: environment steps
    :param window: steps
    :return: at each step, the mean over seeds of the paper's measure (the mean return of the training episodes that
        ended in the last ``window`` steps); ``nan`` where a seed had none (also past the end of a seed's run)
    """
    return np.array([np.mean([run.window_mean(int(step), window) for run in runs]) for step in steps])


def plot_training(env: str, training: list[TrainingEpisodes], budget: str, window: int, path: Path) -> None:
    """
    Plot one task's training episodes, as the paper plots its curves: each seed's episode returns (thin) and, per
    label, the mean over seeds of the paper's measure at every episode end (thick).

    :param env: the task's title
    :param training: the task's training episodes (one per run)
    :param budget: ``"cpu"`` or ``"paper"``
    :param window: the paper's window in steps
    :param path: the PNG file to write
    """
    figure, axis = _new_figure()
    for index, label in enumerate(dict.fromkeys(episodes.label for episodes in training)):
        runs = [episodes for episodes in training if episodes.label == label]
        color = f"C{index}"
        for run in runs:
            axis.plot(run.end_steps, run.returns, color=color, alpha=0.25, linewidth=0.8)
        steps = np.unique(np.concatenate([run.end_steps for run in runs]))
        mean = training_curve(runs, steps, window)
        axis.plot(steps, mean, color=color, linewidth=2, label=f"{label} ({_seeds(len(runs))}; thick: last {window} steps)")
    _save_figure(figure, axis, f"{env}: training episodes ({budget} budget)", "training episode return", path)


def write_report(
    results: list[JobResult],
    envs: list[str],
    budget: str,
    output: Path,
    paper_names: dict[str, str] | None = None,
    window: int = PAPER_WINDOW,
    reference: str | None = "POPLIN-P (MPC)",
    protocol_steps: list[int] | None = None,
) -> Path:
    """
    Write ``results.md``, ``results.json``, one ``curves_<task>.png`` (evaluations) and one ``training_<task>.png``
    (training episodes) per task.

    :param results: every job's result
    :param envs: the tasks, in table order
    :param budget: ``"cpu"`` or ``"paper"``
    :param output: the report folder
    :param paper_names: env id -> the paper's task name, for the paper suite's table (``None``: one row per task)
    :param window: steps of the paper's protocol
    :param reference: the column whose final return the others must reach
    :param protocol_steps: more steps to apply the paper's protocol at
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
        interrupted: dict[str, int] = {}
        for result in env_results:
            expected[result.job.column] = expected.get(result.job.column, 0) + 1
            if result.unfinished:
                interrupted[result.job.column] = interrupted.get(result.job.column, 0) + 1
            if result.run_dir is None:
                absent = missing if result.missing else failed
                absent[result.job.column] = absent.get(result.job.column, 0) + 1
        found = [result for result in env_results if result.run_dir is not None]
        training = [episodes for result in found if (episodes := load_training(result)) is not None]
        budget_step = min((result.job.n_timesteps for result in env_results), default=None)
        summary = summarize(
            env, curves, failed, expected, training, budget_step, window, reference, missing, protocol_steps, interrupted
        )
        summary.name = (paper_names or {}).get(env, env)
        summaries.append(summary)
        if curves:
            title = env if summary.name == env else f"{summary.name} ({env})"
            plot_curves(title, curves, budget, output / f"curves_{env_name(env)}.png")
        if training:
            title = env if summary.name == env else f"{summary.name} ({env})"
            plot_training(title, training, budget, window, output / f"training_{env_name(env)}.png")
    table = output / "results.md"
    if paper_names:
        write_paper_table(summaries, budget, table)
    else:
        write_table(summaries, budget, table)
    reached = [(result, load_training(result)) for result in results if result.unfinished]
    if reached:
        lines = [
            "",
            "## Unfinished runs",
            "",
            "Interrupted runs, in the tables above as far as they got (`--include-unfinished`):",
            "",
            "| task | column | seed | steps reached (last episode's end) |",
            "|---|---|---|---|",
        ]
        for result, episodes in reached:
            steps = "—" if episodes is None else str(episodes.n_timesteps)
            lines.append(f"| {result.job.env} | {result.job.column.upper()} | {result.job.seed} | {steps} |")
        table.write_text(table.read_text() + "\n".join(lines) + "\n")
    timed = [(result, episodes) for result in results if result.run_dir is not None and (episodes := load_training(result))]
    times = {id(result): episodes.run_time() for result, episodes in timed}
    if timed:
        table.write_text(table.read_text() + "\n".join(run_time_lines(timed)) + "\n")
    runs = []
    for result in results:
        run = {**asdict(result.job), "run_dir": result.run_dir, "returncode": result.returncode}
        if id(result) in times:
            run |= {"run_time_s": times[id(result)][0], "interrupted_episodes": times[id(result)][1]}
        runs.append({**run, "unfinished": True} if result.unfinished else run)
    suite = "paper" if paper_names else "all"
    tasks = [summary.to_json() for summary in summaries]
    report = {"budget": budget, "suite": suite, "reference": reference, "tasks": tasks, "runs": runs}
    (output / "results.json").write_text(json.dumps(report, indent=2))
    return table
