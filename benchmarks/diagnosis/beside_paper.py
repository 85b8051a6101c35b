"""
A head-to-head report beside a paper's table: each column's seeds by the paper's protocol against the paper's mean and
spread (Welch's t-test from the paper's summary statistics), the ratio of two columns' means here and in the paper
with an exact permutation test between them, and the posture check of each final agent.

    python benchmarks/diagnosis/beside_paper.py --report benchmarks/suite_cpu/PETSCheetah-v0-h30/headline \\
        --paper POPLIN-P=12228,5653 POPLIN-A=4651,1089 PETS=4205,789 SAC=1746,839 TD3=219,593 --paper-seeds 4 \\
        --ratio POPLIN-P PETS --posture benchmarks/suite_cpu/PETSCheetah-v0-h30/posture.jsonl --write

``--report`` is a ``compare`` report folder: its ``results.json`` gives each column's per-seed values of the paper's
protocol (the mean return of the training episodes that ended in the last window of steps) at the task's budget.
``--paper LABEL=MEAN,STD`` are the paper's numbers for the same measure and step, ``LABEL`` a column of the report
(``PETS``, ``POPLIN-P``, ``SAC``). ``--write`` puts the section into the report's ``results.md`` (replacing the one
an earlier run put there) and its numbers into ``results.json`` under ``beside_paper``; without it the section is
printed. ``--posture`` is the JSON-lines file of ``cheetah_posture.py --record`` (lines tagged ``column=``, ``seed=``,
``run=``; lines planned with other settings, ``--set``, are left out).
"""

from __future__ import annotations

import argparse
import itertools
import json
import math
from pathlib import Path
from typing import Any

import numpy as np
from scipy import stats

HEADING = "## Beside the paper"


def parse_paper(items: list[str]) -> dict[str, tuple[float, float]]:
    """:return: ``LABEL=MEAN,STD`` strings as label -> (mean, std); a clear error for any other spelling"""
    paper: dict[str, tuple[float, float]] = {}
    for item in items:
        label, _, numbers = item.partition("=")
        parts = numbers.split(",")
        try:
            if not label or len(parts) != 2:
                raise ValueError
            mean, std = float(parts[0]), float(parts[1])
        except ValueError:
            raise SystemExit(f"--paper takes LABEL=MEAN,STD, e.g. --paper PETS=4205,789; got {item!r}") from None
        if std < 0:
            raise SystemExit(f"--paper {item}: a standard deviation is not negative")
        paper[label] = (mean, std)
    return paper


def welch_from_stats(values: list[float], mean: float, std: float, count: int) -> dict[str, float]:
    """
    Welch's unequal-variance t-test of our seeds against a published mean ± std over ``count`` seeds.

    :param values: our per-seed values (at least 2)
    :param mean: the published mean
    :param std: the published standard deviation, taken as the sample one (over ``count - 1``)
    :param count: the published number of seeds (at least 2)
    :return: ``t`` (ours minus theirs over its standard error), ``df`` (Welch-Satterthwaite) and two-sided ``p``
    """
    if len(values) < 2 or count < 2:
        raise ValueError(f"Welch's test needs at least 2 values a side; got {len(values)} here and {count} published")
    ours = np.asarray(values, dtype=np.float64)
    share_ours = ours.var(ddof=1) / ours.size
    share_theirs = std**2 / count
    error = math.sqrt(share_ours + share_theirs)
    if error == 0.0:
        raise ValueError("Welch's test: both sides have no spread")
    t = (ours.mean() - mean) / error
    df = (share_ours + share_theirs) ** 2 / (share_ours**2 / (ours.size - 1) + share_theirs**2 / (count - 1))
    return {"t": float(t), "df": float(df), "p": float(2 * stats.t.sf(abs(t), df))}


def permutation_p(first: list[float], second: list[float]) -> float:
    """
    The exact two-sided permutation test of a difference of means: the share of all ways to split the pooled values
    into groups of the two sizes whose difference of means is at least as large in magnitude as the observed one.

    :return: the p-value; with 4 seeds a side the smallest possible is 2 / 70
    """
    pooled = np.asarray(list(first) + list(second), dtype=np.float64)
    size, total = len(first), pooled.sum()
    if size == 0 or len(second) == 0:
        raise ValueError("a permutation test needs values on both sides")
    observed = abs(np.mean(first) - np.mean(second))
    tolerance = 1e-9 * max(1.0, float(np.max(np.abs(pooled))))
    extreme = splits = 0
    for chosen in itertools.combinations(range(pooled.size), size):
        part = pooled[list(chosen)].sum()
        difference = abs(part / size - (total - part) / (pooled.size - size))
        extreme += difference >= observed - tolerance
        splits += 1
    return extreme / splits


def posture_lines(path: Path) -> list[dict[str, Any]]:
    """
    :return: each final agent's latest posture line at its trained settings (lines with ``settings`` planned at
        another budget are left out), ordered by column then seed
    """
    latest: dict[tuple[str, int, str], dict[str, Any]] = {}
    for text in path.read_text().splitlines():
        if not text.strip():
            continue
        line = json.loads(text)
        if line.get("settings") or "column" not in line or "seed" not in line:
            continue
        latest[(line["column"], int(line["seed"]), line.get("run", ""))] = line
    return [latest[key] for key in sorted(latest)]


def _number(value: float) -> str:
    return f"{value:.0f}"


def beside_paper(
    protocol: dict[str, Any],
    paper: dict[str, tuple[float, float]],
    paper_seeds: int,
    ratio: tuple[str, str] | None = None,
    posture: list[dict[str, Any]] | None = None,
    note: str = "",
) -> tuple[list[str], dict[str, Any]]:
    """
    :param protocol: a task's ``paper_protocol`` entry of a report's ``results.json`` (``step``, ``window``, and
        ``labels``: label -> ``seeds``, ``values``)
    :param paper: label -> the paper's (mean, std) at the same step
    :param paper_seeds: the paper's number of seeds
    :param ratio: two labels (numerator, denominator) whose ratio of means is compared with the paper's
    :param posture: :func:`posture_lines`
    :param note: a paragraph under the heading (what differs from the paper's set-up)
    :return: the section's Markdown lines and its numbers
    """
    labels = protocol.get("labels", {})
    step = protocol.get("step")
    numbers: dict[str, Any] = {"step": step, "paper_seeds": paper_seeds, "columns": {}}
    lines = [HEADING, ""]
    if note:
        lines += [note, ""]
    lines += [
        f"The paper's protocol at step {step}: the mean return of the training episodes that ended in the last "
        f"{protocol.get('window')} steps, mean ± std over seeds (std over n here, as every table of this report; "
        f"Welch's test takes the sample std of both sides, the paper's ± as one over its {paper_seeds} seeds).",
        "",
        f"| column | the paper ({paper_seeds} seeds) | here | here, each seed | here - paper | Welch's test |",
        "|---|---|---|---|---|---|",
    ]
    for label in list(paper) + [label for label in labels if label not in paper]:
        entry = labels.get(label)
        mean_paper, std_paper = paper.get(label, (math.nan, math.nan))
        paper_cell = "—" if label not in paper else f"{_number(mean_paper)} ± {_number(std_paper)}"
        if entry is None or not entry.get("values"):
            lines.append(f"| {label} | {paper_cell} | not run here | — | — | — |")
            continue
        values = [float(value) for value in entry["values"]]
        seeds = [int(seed) for seed in entry["seeds"]]
        here = np.asarray(values)
        column: dict[str, Any] = {"seeds": seeds, "values": values, "mean": float(here.mean()), "std": float(here.std())}
        count = f"{len(values)} seed{'' if len(values) == 1 else 's'}"
        each = ", ".join(f"s{seed}: {_number(value)}" for seed, value in zip(seeds, values, strict=True))
        difference = test = "—"
        if label in paper:
            column.update(paper_mean=mean_paper, paper_std=std_paper)
            gap = here.mean() - mean_paper
            difference = f"{gap:+.0f}" + (f" ({gap / mean_paper:+.0%})" if mean_paper else "")
            if len(values) >= 2 and paper_seeds >= 2:
                column["welch"] = welch_from_stats(values, mean_paper, std_paper, paper_seeds)
                welch = column["welch"]
                test = f"t = {welch['t']:.2f}, df = {welch['df']:.1f}, p = {welch['p']:.3f}"
            else:
                test = "needs 2 seeds"
        numbers["columns"][label] = column
        lines.append(
            f"| {label} | {paper_cell} | {_number(here.mean())} ± {_number(here.std())} ({count}) | {each} | "
            f"{difference} | {test} |"
        )
    if ratio is not None:
        top, bottom = ratio
        ours = (labels.get(top) or {}).get("values"), (labels.get(bottom) or {}).get("values")
        lines.append("")
        if not ours[0] or not ours[1]:
            lines.append(f"{top} / {bottom}: not both run here.")
        else:
            first, second = [float(v) for v in ours[0]], [float(v) for v in ours[1]]
            above = sum(a > b for a in first for b in second)
            splits = math.comb(len(first) + len(second), len(first))
            ratio_numbers: dict[str, Any] = {
                "columns": [top, bottom],
                "here": float(np.mean(first) / np.mean(second)),
                "pairs_above": above,
                "pairs": len(first) * len(second),
                "permutation_p": permutation_p(first, second),
                "splits": splits,
            }
            paper_ratio = ""
            if top in paper and bottom in paper and paper[bottom][0]:
                ratio_numbers["paper"] = paper[top][0] / paper[bottom][0]
                paper_ratio = f", {ratio_numbers['paper']:.2f}x in the paper"
            numbers["ratio"] = ratio_numbers
            lines.append(
                f"{top} / {bottom}: {ratio_numbers['here']:.2f}x here ({len(first)} and {len(second)} seeds)"
                f"{paper_ratio}; a {top} seed above a {bottom} seed in {above} of {len(first) * len(second)} pairs; "
                f"exact permutation test of the difference of means over all {splits} splits of the "
                f"{len(first) + len(second)} seeds: two-sided p = {ratio_numbers['permutation_p']:.3f} (never below "
                f"{2 / splits if len(first) == len(second) else 1 / splits:.3f} with these group sizes)."
            )
    if posture:
        lines += [
            "",
            "The posture check of each final agent (`cheetah_posture.py`: one 1000-step MPC episode at its trained settings):",
            "",
            "| column | seed | start seed | MPC return | steps upside down | net turns of the torso |",
            "|---|---|---|---|---|---|",
        ]
        numbers["posture"] = []
        for line in posture:
            turns = "—" if line.get("turns") is None else f"{line['turns']:.1f}"
            lines.append(
                f"| {line['column']} | {line['seed']} | {line.get('start_seed', '—')} | {line['return']:.0f} | "
                f"{line['upside_down']:.1%} | {turns} |"
            )
            numbers["posture"].append(
                {key: line.get(key) for key in ("column", "seed", "run", "start_seed", "return", "upside_down", "turns")}
            )
    return lines, numbers


def write_section(report: Path, lines: list[str], numbers: dict[str, Any]) -> None:
    """Put the section into ``report/results.md`` (in place of an earlier one) and its numbers into ``results.json``."""
    table = report / "results.md"
    text = table.read_text().splitlines()
    if HEADING in text:
        start = text.index(HEADING)
        end = next((i for i in range(start + 1, len(text)) if text[i].startswith("## ")), len(text))
        text = text[:start] + lines + (["", *text[end:]] if end < len(text) else [])
    else:
        text = [*text, "", *lines]
    table.write_text("\n".join(text).rstrip("\n") + "\n")
    results = report / "results.json"
    data = json.loads(results.read_text())
    data["beside_paper"] = numbers
    results.write_text(json.dumps(data, indent=2))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--report", type=Path, required=True, help="a compare report folder (with results.json)")
    parser.add_argument("--env", help="the task, when the report has several")
    parser.add_argument("--paper", nargs="+", required=True, metavar="LABEL=MEAN,STD", help="the paper's numbers")
    parser.add_argument("--paper-seeds", type=int, required=True, help="the paper's number of seeds")
    parser.add_argument("--ratio", nargs=2, metavar=("TOP", "BOTTOM"), help="two columns whose ratio is compared")
    parser.add_argument("--posture", type=Path, help="cheetah_posture.py's --record file")
    parser.add_argument("--note", default="", help="a paragraph under the heading")
    parser.add_argument("--write", action="store_true", help="into the report's results.md and results.json")
    args = parser.parse_args()
    paper = parse_paper(args.paper)
    report = json.loads((args.report / "results.json").read_text())
    tasks = [task for task in report["tasks"] if args.env in (None, task["env"])]
    if len(tasks) != 1:
        names = [task["env"] for task in report["tasks"]]
        raise SystemExit(f"{args.report}/results.json has the tasks {names}: name one with --env")
    posture = posture_lines(args.posture) if args.posture is not None and args.posture.exists() else None
    ratio = (args.ratio[0], args.ratio[1]) if args.ratio else None
    lines, numbers = beside_paper(tasks[0]["paper_protocol"], paper, args.paper_seeds, ratio, posture, args.note)
    if args.write:
        write_section(args.report, lines, numbers)
        print(f"{args.report / 'results.md'}: {HEADING[3:]}")
    else:
        print("\n".join(lines))


if __name__ == "__main__":
    main()
