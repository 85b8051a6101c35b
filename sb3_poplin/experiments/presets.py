"""
The packaged hyperparameter files (``sb3_poplin/hyperparams/<algo>.yml``, rl-zoo3's format) and the POPLIN settings
read from them: the one place where the paper's and the CPU budgets' settings are written down. The rl-zoo3 front
end, the demo, the benchmarks and the tests all take their settings from here.
"""

from __future__ import annotations

import inspect
from pathlib import Path
from typing import Any

import yaml

from sb3_poplin.common import check_choice

HYPERPARAMS_DIR = Path(__file__).resolve().parent.parent / "hyperparams"
# algorithms with a packaged hyperparameter file (poplin also has the CPU-sized poplin_cpu.yml)
PACKAGED_ALGOS = ("poplin", "sac", "td3", "ppo", "crossq", "tqc")
BUDGETS = ("paper", "cpu")
# keys of a POPLIN zoo entry that are not POPLIN keyword arguments (the run's budget, the env's kwargs)
ZOO_KEYS = ("n_timesteps", "env_kwargs")


def config_path(algo: str, budget: str = "paper") -> Path | None:
    """
    The packaged hyperparameter file of an algorithm.

    :param algo: rl-zoo3 algorithm name, e.g. ``"poplin"`` or ``"sac"``
    :param budget: ``"paper"`` (the paper's planner settings) or ``"cpu"`` (planner budgets for 2 CPU cores);
        only POPLIN has a CPU file, the other algorithms' settings do not depend on it
    :return: the path, or ``None`` when the package ships no file for ``algo``
    """
    check_choice("budget", budget, BUDGETS)
    if algo not in PACKAGED_ALGOS:
        return None
    name = f"{algo}_cpu" if algo == "poplin" and budget == "cpu" else algo
    return HYPERPARAMS_DIR / f"{name}.yml"


def load_config(path: str | Path) -> dict[str, dict[str, Any]]:
    """
    Read an rl-zoo3 hyperparameter file (YAML anchors and merge keys resolved).

    :param path: the ``.yml`` file
    :return: env id -> hyperparameters
    """
    with open(path) as file:
        content = yaml.safe_load(file)
    if not isinstance(content, dict):
        raise ValueError(f"{path} is not an rl-zoo3 hyperparameter file (expected a mapping of env ids)")
    return content


def poplin_settings(env_id: str, budget: str = "cpu", **overrides: Any) -> dict[str, Any]:
    """
    POPLIN's keyword arguments for an env from the packaged file: ``POPLIN(env=env_id, **poplin_settings(env_id))``.

    :param env_id: an env with an entry in the file
    :param budget: ``"cpu"`` (``poplin_cpu.yml``) or ``"paper"`` (``poplin.yml``)
    :param overrides: keyword arguments that replace the file's (e.g. ``policy="pets"``)
    :return: the entry without :data:`ZOO_KEYS`, lists as tuples, with the overrides
    :raises ValueError: no entry for the env, or a key POPLIN does not take (an rl-zoo3 option such as ``normalize``)
    """
    path = config_path("poplin", budget)
    assert path is not None
    entries = load_config(path)
    if env_id not in entries:
        raise ValueError(
            f"{path.name} has no entry for {env_id!r}. Entries: {sorted(entries)}. Pick one of them, or train with "
            "`sb3-poplin-zoo train --algo poplin --env ID --conf-file FILE` and a file of your own."
        )
    entry = {key: value for key, value in {**entries[env_id], **overrides}.items() if key not in ZOO_KEYS}
    from sb3_poplin.poplin import POPLIN  # the settings are POPLIN's keyword arguments

    accepted = set(inspect.signature(POPLIN.__init__).parameters) - {"self", "env", "_init_setup_model"}
    unknown = sorted(set(entry) - accepted)
    if unknown:
        raise ValueError(
            f"POPLIN does not take {unknown} (from the {env_id!r} entry of {path.name} or the overrides); its settings "
            f"are its keyword arguments: {sorted(accepted)}. For rl-zoo3 options such as normalize or n_envs, train "
            "with sb3-poplin-zoo."
        )
    return {key: tuple(value) if isinstance(value, list) else value for key, value in entry.items()}
