"""
MPC against policy control over training (the paper's figures of both modes): the evaluation files that rl-zoo3
runs write (``evaluations.npz`` for the zoo's MPC evaluation, ``evaluations_policy.npz`` for policy control;
:class:`sb3_poplin.callbacks.ControlModesEvalCallback` writes ``evaluations_mpc.npz`` / ``evaluations_policy.npz``),
gathered over every run (seed) of an env and drawn as mean ± std.
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from huggingface_sb3 import EnvironmentName

# control mode -> evaluation files that hold it, first found wins
MODE_FILES = {"mpc": ("evaluations.npz", "evaluations_mpc.npz"), "policy": ("evaluations_policy.npz",)}


@dataclass
class Curves:
    """One control mode over all runs: per run the mean evaluation return at every evaluation."""

    mode: str
    timesteps: np.ndarray  # [T], the evaluations all runs have
    returns: np.ndarray  # [runs, T]
    runs: list[str]

    @property
    def mean(self) -> np.ndarray:
        return self.returns.mean(axis=0)

    @property
    def std(self) -> np.ndarray:
        return self.returns.std(axis=0)


def find_runs(log_folder: str | Path, env_id: str) -> list[Path]:
    """The rl-zoo3 run folders of an env under ``log_folder`` (``<algo>/<env name>_<run id>[_<uuid>]``), sorted."""
    pattern = re.compile(re.escape(str(EnvironmentName(env_id))) + r"_\d+(_[0-9a-f-]+)?$")
    folders = {path.parent for path in Path(log_folder).rglob("evaluations*.npz") if pattern.match(path.parent.name)}
    return sorted(folders)


def control_curves(log_folder: str | Path, env_id: str) -> dict[str, Curves]:
    """
    :param log_folder: a zoo log folder (``-f``), searched recursively
    :param env_id: the env of the runs
    :return: control mode -> its curves (modes without any file are left out)
    :raises FileNotFoundError: when no run of the env is there
    """
    runs = find_runs(log_folder, env_id)
    if not runs:
        raise FileNotFoundError(
            f"No rl-zoo3 run of {env_id} with evaluation files under {log_folder} (looked for "
            f"<algo>/{EnvironmentName(env_id)}_<id>/evaluations*.npz): pass the folder given to the zoo's -f."
        )
    curves = {}
    for mode, names in MODE_FILES.items():
        found = []
        for run in runs:
            path = next((run / name for name in names if (run / name).is_file()), None)
            if path is None:
                continue
            with np.load(path) as data:
                timesteps = np.asarray(data["timesteps"])
                results = np.asarray(data["results"], dtype=float).reshape(len(timesteps), -1).mean(axis=1)
            if len(timesteps):
                found.append((run.name, timesteps, results))
        if found:
            length = min(len(t) for _, t, _ in found)  # runs stopped at different points: the evaluations all have
            curves[mode] = Curves(
                mode, found[0][1][:length], np.stack([r[:length] for _, _, r in found]), [name for name, _, _ in found]
            )
    return curves


def plot_control_curves(curves: dict[str, Curves], path: str, title: str = "") -> None:
    """Mean ± std over runs of each control mode's evaluation return."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6, 4))
    for mode, curve in curves.items():
        ax.plot(curve.timesteps, curve.mean, label=f"{mode} ({len(curve.runs)} runs)")
        ax.fill_between(curve.timesteps, curve.mean - curve.std, curve.mean + curve.std, alpha=0.25)
    ax.set_xlabel("env steps")
    ax.set_ylabel("evaluation return")
    ax.set_title(title)
    ax.legend()
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)
