"""
Saved agents: a zip is checked before SB3 reads it (a clear error for anything that is not a complete POPLIN zip).

Beside SB3's ``data`` and the networks' and optimizers' ``.pth`` files, a POPLIN zip holds the MPC controller's state
(``mpc.pth``: the planner's random generator and warm start), for POPLIN-A/P the distiller's (``distiller.pth``: the
planned steps not yet distilled and the distillation window), and in ``data`` the agent's model hooks
(``model_hooks``) and the release that saved it (``sb3_poplin_version``). What zips of earlier releases need is in
:mod:`sb3_poplin.compat`.
"""

from __future__ import annotations

import difflib
import io
import json
import os
import pathlib
import warnings
import zipfile
from collections.abc import Iterable
from typing import Any

from sb3_poplin import compat


def current_release() -> str:
    """:return: this package's release (``sb3_poplin.__version__``), which ``POPLIN.save`` records in a zip"""
    from sb3_poplin import __version__  # here, not at the top: the package imports this module before setting it

    return __version__


def check_saved_agent(
    path: str | pathlib.Path | io.BufferedIOBase,
    custom_objects: dict[str, Any] | None = None,
    hooks_given: bool = False,
    given: Iterable[str] = (),
    settings: Iterable[str] = (),
) -> dict[str, Any]:
    """
    Reject, with the reason and the fix, anything that is not a complete POPLIN zip, and keywords of ``load`` that
    would set nothing an agent reads.

    :param path: what was given to ``POPLIN.load``
    :param custom_objects: ``load``'s
    :param hooks_given: ``load`` was given ``model_hooks=``
    :param given: the names of the keywords ``load`` was given to replace saved attributes (SB3 sets each on the
        agent, a misspelt one too, where it is then never read)
    :param settings: the names of the agent's settings (:class:`sb3_poplin.variants.Settings`): each may be given,
        also to a zip of an earlier release that does not hold it
    :return: the attributes to restore with the agent that a zip of an earlier release does not hold
        (:func:`sb3_poplin.compat.legacy_attributes`); none for a zip of this release
    :raises FileNotFoundError: no file at ``path`` (nor ``path.zip``)
    :raises ValueError: not a zip, corrupted, saved by another algorithm, or incomplete
    :raises TypeError: a keyword in ``given`` that is neither a setting nor an attribute the zip holds
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
            f"sb3_poplin {compat.LEGACY_VERSION} (_saved_planner_state in data): it was not written by a released "
            "POPLIN.save. Save the agent again with POPLIN.save."
        )
    if "model_hooks" in data and not hooks_given:
        check_saved_hooks(data["model_hooks"], where)
    restored = compat.legacy_attributes(names, data, where, custom_objects, hooks_given)
    known = {*settings, *data, *restored, "model_hooks"}
    unknown = [key for key in given if key not in known]
    if unknown:
        hints = []
        for key in unknown:
            close = difflib.get_close_matches(key, sorted(known), 1)
            hints.append(f"{key!r} (did you mean {close[0]!r}?)" if close else repr(key))
        raise TypeError(
            f"POPLIN.load() got keyword(s) {', '.join(hints)} that are neither a setting of a POPLIN agent nor an "
            f"attribute {where} holds: they would be set on the agent and never read. Settings: {', '.join(settings)}."
        )
    return restored


def check_saved_hooks(serialized: Any, where: str) -> None:
    """
    :param serialized: a zip's ``model_hooks`` as its data holds it
    :param where: the zip, named in the error
    :raises ValueError: they do not unpickle (a function or class they name is gone), with the fix
    """
    from stable_baselines3.common.save_util import json_to_data

    from sb3_poplin.tasks.hooks import ModelHooks

    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # SB3 warns and drops some of what does not unpickle: said below
            hooks = json_to_data(json.dumps({"model_hooks": serialized})).get("model_hooks")
        problem = None if isinstance(hooks, ModelHooks) else f"got {type(hooks).__name__}"
    except Exception as error:  # anything unpickling can raise
        problem = f"{type(error).__name__}: {error}"
    if problem is not None:
        raise ValueError(
            f"{where}: its model hooks cannot be read ({problem}). Pass them, and skip the saved ones: "
            "POPLIN.load(path, model_hooks=ModelHooks(...), custom_objects={'model_hooks': None, 'policy_kwargs': {}})."
        )
