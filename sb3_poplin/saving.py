"""
Saved agents: checking a zip before SB3 reads it, and reading the zips of earlier releases.

Since 0.2.0 a POPLIN zip holds, beside SB3's ``data`` and the networks' and optimizers' ``.pth`` files, the MPC
controller's state (``mpc.pth``: the planner's random generator and warm start) and, for POPLIN-A/P, the
distiller's (``distiller.pth``: the planned steps not yet distilled and the distillation window). Release 0.1.0 kept
both inside ``data`` as one pickled ``_saved_planner_state`` dict; :func:`upgrade_legacy_state` turns it into the two
state dicts, so those zips load as they are.

Since 0.3.0 a zip records the release that saved it (``sb3_poplin_version`` in ``data``); :func:`saved_release`
infers it for the zips of earlier releases, and :func:`check_saved_agent` gives what such a zip needs to continue as
it was trained.
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
# the key of a zip's data (and the attribute of a loaded POPLIN) naming the release that saved it
VERSION_KEY = "sb3_poplin_version"
# settings added in 0.3.0, with the behaviour of the releases before: a zip without them continues as it was trained
SETTINGS_BEFORE_0_3: dict[str, Any] = dict(
    whitening="function_from_raw", avg_update="add", distill_target="executed", standardise_targets=True
)
# the key of a zip's data (and the attribute of a loaded POPLIN) naming the release whose task hooks its model was
# trained with (``TaskSpec.model_hooks``: PETSCheetah's model has PETS's hooks since 0.3.0). Zips from before it was
# recorded: the release that saved them, or 0.2.0 for a zip that 0.3.0 saved with ``task_model_hooks`` False (a 0.1.0
# or 0.2.0 agent saved again)
HOOKS_RELEASE_KEY = "model_hooks_release"


def current_release() -> str:
    """:return: this package's release (``sb3_poplin.__version__``), which ``POPLIN.save`` records in a zip"""
    from sb3_poplin import __version__  # here, not at the top: the package imports this module before setting it

    return __version__


def saved_release(names: set[str], data: dict[str, Any]) -> str:
    """
    The release that saved a POPLIN zip: recorded in its ``data`` since 0.3.0, inferred for earlier zips from what
    they hold.

    :param names: the zip's member names
    :param data: the zip's ``data`` (SB3's JSON)
    :return: the recorded release; else ``"0.1.0"`` without ``mpc.pth``, ``"0.2.0"`` without one of the settings
        added in 0.3.0 (:data:`SETTINGS_BEFORE_0_3`), ``"0.3.0"`` otherwise (saved before releases recorded
        themselves)
    """
    if VERSION_KEY in data:
        return str(data[VERSION_KEY])
    if "mpc.pth" not in names:
        return LEGACY_VERSION
    if any(key not in data for key in SETTINGS_BEFORE_0_3):
        return "0.2.0"
    return "0.3.0"


def check_saved_agent(path: str | pathlib.Path | io.BufferedIOBase) -> dict[str, Any]:
    """
    Reject, with the reason and the fix, anything that is not a complete POPLIN zip.

    :param path: what was given to ``POPLIN.load``
    :return: the attributes to restore with the agent that the zip does not hold: the settings its release did not
        save, with that release's behaviour (:data:`SETTINGS_BEFORE_0_3`), the release whose task hooks its model was
        trained with (:data:`HOOKS_RELEASE_KEY`) and the release that saved it (``sb3_poplin_version``,
        :func:`saved_release`) when the zip does not record them
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
    release = saved_release(names, data)
    restored = {key: value for key, value in SETTINGS_BEFORE_0_3.items() if key not in data}
    if HOOKS_RELEASE_KEY not in data:
        restored[HOOKS_RELEASE_KEY] = "0.2.0" if data.get("task_model_hooks") is False else release
    if VERSION_KEY not in data:
        restored[VERSION_KEY] = release
    return restored


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
