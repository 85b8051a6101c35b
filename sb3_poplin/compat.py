"""
Zips of earlier releases: everything ``POPLIN.load`` does for them, in one place.

The policy (also in docs/usage.md, "Saving, loading and resuming"): a zip of a published release (0.1.0, 0.2.0,
0.3.0, 0.5.0) loads, predicts and continues training as it did under that release, until 1.0.0; zips of the development
numbers 0.4.0 to 0.4.2 (never published; the project's own benchmark agents are of them) load the same way, until
0.6.0. A zip of 0.5.0 or later needs nothing from this module. Each shim below names the zips it serves and the release
that removes it; ``tests/test_save_load.py`` runs every zip listed in ``tests/data/manifest.json`` through them.
"""

from __future__ import annotations

import json
import warnings
from typing import Any

import torch as th
from stable_baselines3.common.save_util import json_to_data

from sb3_poplin.tasks.hooks import ModelHooks

# the release of zips that record none and keep the planner state in data (``_saved_planner_state``)
LEGACY_VERSION = "0.1.0"
# the key of a zip's data naming the release that saved it (recorded since 0.3.0)
VERSION_KEY = "sb3_poplin_version"

# compat (zips of 0.1.0 and 0.2.0; remove in 1.0.0): settings added in 0.3.0, with the behaviour of the releases
# before, so that a zip without them continues as it was trained
SETTINGS_BEFORE_0_3: dict[str, Any] = dict(
    whitening="function_from_raw", avg_update="add", distill_target="executed", standardise_targets=True
)

# compat (zips of <= 0.4.2; remove in 1.0.0): attributes of their data that no release reads any more: 0.3.0's
# ``task_model_hooks`` and 0.4.x's ``model_hooks_release`` (the hooks were looked up by release; they are now read
# from the zip, :func:`saved_hooks`), and the rollout's ``_collecting`` flag of <= 0.4.2
DROPPED_DATA_KEYS = ("task_model_hooks", "model_hooks_release", "_collecting")


def saved_release(names: set[str], data: dict[str, Any]) -> str:
    """
    The release that saved a POPLIN zip: recorded in its ``data`` since 0.3.0, inferred for earlier zips from what
    they hold (compat: zips of 0.1.0 and 0.2.0; remove in 1.0.0).

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


def saved_hooks(data: dict[str, Any], where: str, custom_objects: dict[str, Any] | None = None) -> ModelHooks:
    """
    The hooks a zip without a ``model_hooks`` record was trained with: those its networks were built with, which
    every release saved in the policy's keyword arguments (compat: zips of <= 0.4.2; remove in 1.0.0).

    :param data: the zip's ``data`` (SB3's JSON, not yet deserialized)
    :param where: the zip, named in the error
    :param custom_objects: ``load``'s (its ``policy_kwargs`` is not the zip's: not read here)
    :raises ValueError: the saved hooks cannot be read (a function they name no longer exists)
    """
    if "policy_kwargs" not in data:
        raise ValueError(f"{where} has no policy_kwargs: it was not written by a released POPLIN.save. Save the agent again.")
    problem = "a function they name no longer exists"
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # SB3 warns and drops some of what does not unpickle: the error says it
            serialized = json.dumps({"policy_kwargs": data["policy_kwargs"]})  # the zip's own, not custom_objects'
            kwargs = json_to_data(serialized).get("policy_kwargs")
    except Exception as error:  # anything unpickling can raise (a module or attribute gone, a changed class)
        kwargs, problem = None, f"{type(error).__name__}: {error}"
    if not isinstance(kwargs, dict) or "model_input_exclude" not in kwargs:  # every release saved it
        raise ValueError(
            f"{where}: the model hooks its networks were built with (in its policy_kwargs) cannot be read ({problem}). "
            "Pass them, and skip the saved ones: POPLIN.load(path, model_hooks=ModelHooks(...), "
            "custom_objects={'policy_kwargs': {}})."
        )
    return ModelHooks.from_network_kwargs(kwargs)


def legacy_attributes(
    names: set[str], data: dict[str, Any], where: str, custom_objects: dict[str, Any] | None, hooks_given: bool = False
) -> dict[str, Any]:
    """
    What a zip of an earlier release needs restored with the agent, beyond what it holds.

    :param names: the zip's member names
    :param data: the zip's ``data`` (SB3's JSON)
    :param where: the zip, named in errors
    :param custom_objects: ``load``'s
    :param hooks_given: ``load`` was given ``model_hooks=`` (the saved ones are not read)
    :return: attribute -> value: the settings its release did not save (:data:`SETTINGS_BEFORE_0_3`), its model
        hooks (:func:`saved_hooks`) and the release that saved it (:func:`saved_release`) where it records none
    """
    restored: dict[str, Any] = {key: value for key, value in SETTINGS_BEFORE_0_3.items() if key not in data}
    if "model_hooks" not in data and not hooks_given:
        restored["model_hooks"] = saved_hooks(data, where, custom_objects)
    if VERSION_KEY not in data:
        restored[VERSION_KEY] = saved_release(names, data)
    return restored


def upgrade_legacy_state(saved: dict[str, Any], with_distiller: bool) -> dict[str, dict[str, Any]]:
    """
    The ``mpc`` (and ``distiller``) state dicts of a 0.1.0 zip's ``_saved_planner_state`` (compat: zips of 0.1.0;
    remove in 1.0.0).

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
