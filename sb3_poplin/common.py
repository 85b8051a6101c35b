"""Checks shared by every module that takes a setting: one message format for each kind of bad value."""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np
import yaml


def check_choice(name: str, value: Any, accepted: Sequence[str]) -> None:
    """
    :param name: the setting's name, as the user spells it
    :param value: the value given
    :param accepted: the accepted values
    :raises ValueError: ``Unknown <name> <value>; accepted values: [...]`` when ``value`` is not one of them
    """
    if value not in accepted:
        raise ValueError(f"Unknown {name} {value!r}; accepted values: {list(accepted)}")


def check_positive_int(name: str, value: Any, optional: bool = False) -> None:
    """
    :param name: the setting's name
    :param value: the value given
    :param optional: ``None`` is accepted too
    :raises ValueError: ``<name> must be an integer >= 1`` otherwise
    """
    if optional and value is None:
        return
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < 1:
        suffix = " (or None)" if optional else ""
        raise ValueError(f"{name} must be an integer >= 1{suffix}, got {value!r}")


def check_state_keys(owner: str, state: dict[str, Any], keys: Sequence[str], strict: bool) -> None:
    """
    :param owner: what the state belongs to, for the message
    :param state: a state dict given to ``load_state_dict``
    :param keys: the keys it must have
    :param strict: raise when some are missing (else accept a partial state)
    :raises KeyError: naming the missing keys
    """
    missing = set(keys) - set(state)
    if strict and missing:
        raise KeyError(f"{owner} state lacks {sorted(missing)}")


def parse_params(items: Sequence[str]) -> dict[str, Any]:
    """
    Command-line settings as a dict: ``KEY:VALUE`` strings, VALUE read as YAML (as rl-zoo3's ``-params``:
    ``horizon:15``, ``dynamics_net_arch:[200,200]``).

    :raises ValueError: for an item without a key or a ``:``
    """
    params = {}
    for item in items:
        key, sep, value = item.partition(":")
        if not sep or not key:
            raise ValueError(f"--params takes KEY:VALUE pairs (e.g. horizon:15), got {item!r}")
        params[key] = yaml.safe_load(value)
    return params
