"""
Task library: what the planner needs to know about an environment besides the learned dynamics.

A :class:`TaskSpec` holds batched torch functions that rebuild the environment's reward and
termination from a transition ``(obs, action, next_obs)`` — with ``action`` in env units, not the
[-1, 1] scale the replay buffer stores — plus the env kwargs and observation transforms the model
needs. Specs are registered by gymnasium id; :func:`make_task` looks one up. Each spec names the
env version it reproduces, and ``tests/test_tasks.py`` checks it against ``env.step``.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import torch as th

RewardFn = Callable[[th.Tensor, th.Tensor, th.Tensor], th.Tensor]
TerminationFn = Callable[[th.Tensor, th.Tensor, th.Tensor], th.Tensor]


@dataclass(frozen=True)
class TaskSpec:
    """
    Reward, termination and observation handling for one environment.

    :param env_id: gymnasium id the spec reproduces (version included, e.g. ``"Pendulum-v1"``)
    :param reward_fn: ``(obs [B, o], action [B, a] in env units, next_obs [B, o]) -> reward [B]``
    :param termination_fn: same arguments, ``-> bool [B]`` (True where the env terminates),
        or ``None`` when the env never terminates
    :param env_kwargs: keyword arguments the env must be made with for ``reward_fn`` to be exact
        (e.g. keeping the x position in the observation)
    :param model_input_exclude: observation indices that the dynamics model and the policy do not
        see as inputs (e.g. the x position, for translation invariance); the model still predicts
        their change
    :param description: one line for the README task table
    """

    env_id: str
    reward_fn: RewardFn
    termination_fn: TerminationFn | None = None
    env_kwargs: dict[str, Any] = field(default_factory=dict)
    model_input_exclude: tuple[int, ...] = ()
    description: str = ""


_REGISTRY: dict[str, TaskSpec] = {}


def register_task(spec: TaskSpec, overwrite: bool = False) -> None:
    """
    Register a :class:`TaskSpec` under its ``env_id``.

    :param spec: the task specification
    :param overwrite: replace an existing registration instead of raising
    """
    if not isinstance(spec, TaskSpec):
        raise TypeError(f"register_task expects a TaskSpec, got {type(spec).__name__}")
    if spec.env_id in _REGISTRY and not overwrite:
        raise ValueError(f"A task is already registered for {spec.env_id!r}; pass overwrite=True to replace it.")
    _REGISTRY[spec.env_id] = spec


def registered_tasks() -> list[str]:
    """:return: the sorted env ids that have a registered :class:`TaskSpec`"""
    return sorted(_REGISTRY)


def has_task(env_id: str) -> bool:
    """:return: whether ``env_id`` has a registered :class:`TaskSpec`"""
    return env_id in _REGISTRY


def make_task(env_id: str) -> TaskSpec:
    """
    Look up the :class:`TaskSpec` of a gymnasium id.

    :param env_id: the gymnasium id, e.g. ``"Pendulum-v1"``
    :return: the registered spec
    """
    try:
        return _REGISTRY[env_id]
    except KeyError:
        raise ValueError(
            f"No task is registered for {env_id!r}. Registered tasks: {registered_tasks()}. "
            "Pass reward_fn= (and termination_fn=) to POPLIN, or register a TaskSpec with "
            "sb3_poplin.tasks.register_task."
        ) from None


# Built-in tasks register themselves on import.
from sb3_poplin.tasks import classic, mujoco  # noqa: E402, F401

__all__ = ["RewardFn", "TaskSpec", "TerminationFn", "has_task", "make_task", "register_task", "registered_tasks"]
