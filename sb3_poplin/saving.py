"""
Saved agents: checking a zip before SB3 reads it, and reading the zips of earlier releases.

Since 0.2.0 a POPLIN zip holds, beside SB3's ``data`` and the networks' and optimizers' ``.pth`` files, the MPC
controller's state (``mpc.pth``: the planner's random generator and warm start) and, for POPLIN-A/P, the
distiller's (``distiller.pth``: the planned steps not yet distilled and the distillation window). Release 0.1.0 kept
both inside ``data`` as one pickled ``_saved_planner_state`` dict; :func:`upgrade_legacy_state` turns it into the two
state dicts, so those zips load as they are.
"""

from __future__ import annotations

import io
import json
import os
import pathlib
import warnings
import zipfile
from typing import Any

import torch as th

LEGACY_VERSION = "0.1.0"
# settings added in 0.3.0, with the behaviour of the releases before: a zip without them continues as it was trained
SETTINGS_BEFORE_0_3: dict[str, Any] = dict(
    whitening="function_from_raw", avg_update="add", distill_target="executed", standardise_targets=True
)


def check_saved_agent(path: str | pathlib.Path | io.BufferedIOBase) -> dict[str, Any]:
    """
    Reject, with the reason and the fix, anything that is not a complete POPLIN zip.

    :param path: what was given to ``POPLIN.load``
    :return: the settings this zip's release did not save, with that release's behaviour
        (:data:`SETTINGS_BEFORE_0_3`), to restore with the agent
    :raises FileNotFoundError: no file at ``path`` (nor ``path.zip``)
    :raises ValueError: not a zip, corrupted, saved by another algorithm, or incomplete
    """
    where = str(path) if isinstance(path, (str, pathlib.Path)) else "the given file object"
    if isinstance(path, (str, pathlib.Path)) and not os.path.exists(path):
        if os.path.exists(f"{path}.zip"):
            path = f"{path}.zip"
        else:
            raise FileNotFoundError(f"No saved agent at {where} (nor {where}.zip): check the path given to POPLIN.load.")
    start = path.tell() if isinstance(path, io.BufferedIOBase) else None
    try:
        with zipfile.ZipFile(path) as archive:  # type: ignore[arg-type]
            names = set(archive.namelist())
            corrupted = archive.testzip()
            data = json.loads(archive.read("data")) if "data" in names else None
    except (zipfile.BadZipFile, EOFError, OSError, ValueError, KeyError) as error:
        raise ValueError(
            f"{where} is not a readable POPLIN zip (truncated or corrupted? {error}). "
            "Load a file written by POPLIN.save / model.save."
        ) from None
    finally:
        if start is not None:
            path.seek(start)  # type: ignore[union-attr]
    if corrupted is not None:
        raise ValueError(f"{where} is corrupted: its member {corrupted!r} fails the CRC check. Save the agent again.")
    if data is None:  # e.g. cut inside a member that is itself a zip (torch's .pth files are), found instead
        raise ValueError(
            f"{where} is not a readable POPLIN zip (truncated or corrupted? it has no 'data' member). "
            "Load a file written by POPLIN.save / model.save."
        )
    if not isinstance(data, dict) or "variant" not in data:
        saved_by = data.get("policy_class", {}).get("__module__", "unknown") if isinstance(data, dict) else "unknown"
        raise ValueError(
            f"{where} was not saved by POPLIN (its policy comes from {saved_by!r}): "
            "load it with the algorithm that saved it, e.g. stable_baselines3.SAC.load."
        )
    missing = {"policy.pth", "policy.dynamics_optimizer.pth"} - names
    if missing:
        raise ValueError(f"{where} is an incomplete POPLIN zip (missing {sorted(missing)}). Save the agent again.")
    legacy = "mpc.pth" not in names
    if legacy and "_saved_planner_state" not in data:
        raise ValueError(
            f"{where} has neither the MPC state of sb3_poplin >= 0.2.0 (mpc.pth) nor the planner state of "
            f"sb3_poplin {LEGACY_VERSION} (_saved_planner_state in data): it was not written by a released "
            "POPLIN.save. Save the agent again with POPLIN.save."
        )
    return {key: value for key, value in SETTINGS_BEFORE_0_3.items() if key not in data}


def upgrade_legacy_state(saved: dict[str, Any], with_distiller: bool) -> dict[str, dict[str, Any]]:
    """
    The ``mpc`` (and ``distiller``) state dicts of a 0.1.0 zip's ``_saved_planner_state``.

    :param saved: the legacy dict (``generator``, ``warm_start``, ``distill_data``, ``planned``)
    :param with_distiller: the agent has a distiller (POPLIN-A/P)
    :return: parameters to add to what SB3 loads, by attribute name
    """
    upgraded: dict[str, dict[str, Any]] = {"mpc": {"generator": saved["generator"], "warm_start": saved.get("warm_start")}}
    if with_distiller:
        # 0.1.0 dropped failed plans' steps when recording them: every recorded step is kept
        planned = [{**record, "keep": th.ones(len(record["states"]), dtype=th.bool)} for record in saved.get("planned", [])]
        upgraded["distiller"] = {"planned": planned, "data": dict(saved.get("distill_data", {}))}
    elif saved.get("planned") or saved.get("distill_data"):
        warnings.warn("The saved agent has distillation data but no policy network: the data is dropped.", stacklevel=3)
    return upgraded
