"""Append a row to the table of a section of benchmarks/RESULTS.md, creating the section when missing."""

from __future__ import annotations

import os
import platform
import subprocess

RESULTS = os.path.join(os.path.dirname(os.path.abspath(__file__)), "RESULTS.md")


def append_row(section: str, intro: str, header: list[str], row: list[str], path: str = RESULTS) -> None:
    """
    :param section: the section's heading text (without ``## ``): how a row finds its section, so a script keeps the
        heading it was first written with, also where the heading names a path the script has since moved from
        (``benchmarks/planning_speed.py``, now ``benchmarks/speed/planning_speed.py``: ``benchmarks/README.md``)
    :param intro: paragraph written under a new section's heading
    :param header: column names of a new section's table
    :param row: the cells of the row to add, below the last row of the section's table (the one under ``header``;
        text after the table stays after it), or at the section's end when the section has no such table
    :param path: the results file
    """
    lines = open(path).read().splitlines() if os.path.exists(path) else ["# Benchmark results", ""]
    line = "| " + " | ".join(row) + " |"
    heading = f"## {section}"
    header_line = "| " + " | ".join(header) + " |"
    if heading not in lines:
        lines += ["", heading, "", intro, "", header_line, "|" + "---|" * len(header), line]
    else:
        start = lines.index(heading) + 1
        end = start
        while end < len(lines) and not lines[end].startswith("## "):
            end += 1
        if header_line in lines[start:end]:
            end = lines.index(header_line, start) + 1
            while end < len(lines) and lines[end].startswith("|"):
                end += 1
        else:
            while lines[end - 1].strip() == "":
                end -= 1
        lines.insert(end, line)
    with open(path, "w") as file:
        file.write("\n".join(lines) + "\n")


def describe_machine(threads: int | None = None, device: object = None) -> str:
    """
    The machine column of a row: architecture, CPU model and whether it has AMX (bf16 matmuls are several times
    faster with it, slower than fp32 without it), core count, torch version and thread count; for a CUDA run the
    GPU's name and CUDA version first.

    :param threads: torch threads of the run (omitted when None)
    :param device: the run's torch device (or its name); a CUDA device is named in the row
    """
    import torch as th

    info: dict[str, str] = {}
    try:
        with open("/proc/cpuinfo") as file:
            for line in file:
                key, _, value = line.partition(":")
                info.setdefault(key.strip(), value.strip())
    except OSError:
        pass
    amx = "AMX" if "amx_bf16" in info.get("flags", "").split() else "no AMX"
    parts = [platform.machine(), info.get("model name", platform.processor()), amx, f"{os.cpu_count()} cores"]
    if device is not None and th.device(str(device)).type == "cuda":
        parts.insert(0, f"{th.cuda.get_device_name(th.device(str(device)))} (CUDA {th.version.cuda})")
    parts.append(f"torch {th.__version__}")
    if threads is not None:
        parts.append(f"{threads} thread(s)")
    return ", ".join(parts)


# what a run's behaviour depends on: a changed data file (a synced run's csv, json or config.yml, RESULTS.md) is not
# a change of the code that made a record
CODE_PATHS = ("*.py", "sb3_poplin", "setup.cfg", "pyproject.toml", "Makefile")


def code_version(where: str | None = None) -> str:
    """
    The commit of this repository's checkout, ``+changes`` when its code (``CODE_PATHS``: Python files, the package
    with its hyperparameter files, the build files) differs from it; ``unknown`` outside a git checkout.

    :param where: a folder inside the checkout (default: this file's)
    """
    here = where if where is not None else os.path.dirname(os.path.abspath(__file__))
    try:
        head = subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True, cwd=here)
        top = subprocess.run(["git", "rev-parse", "--show-toplevel"], capture_output=True, text=True, cwd=here)
        changed = subprocess.run(
            ["git", "diff", "--quiet", "HEAD", "--", *CODE_PATHS], cwd=top.stdout.strip() or here
        ).returncode
    except OSError:
        return "unknown"
    commit = head.stdout.strip()
    return (commit + ("+changes" if changed else "")) if commit and head.returncode == 0 else "unknown"
