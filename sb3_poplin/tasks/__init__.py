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

import gymnasium as gym
import torch as th

from sb3_poplin.tasks.hooks import ModelHooks

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
        their change. Shorthand for an ``obs_preproc`` that drops them (and the policy's input too)
    :param obs_preproc: PETS's model-input hook, ``obs [..., o] -> features [..., f]`` (torch); ``None``: the
        observation without ``model_input_exclude``. The policy network always sees the raw observation
        (without ``model_input_exclude``)
    :param targ_proc: PETS's model-target hook, ``(obs, next_obs) -> target [..., t]``; ``None``: ``next_obs - obs``
    :param obs_postproc: its inverse, ``(obs, prediction) -> next_obs``; ``None``: ``obs + prediction``.
        ``obs_postproc(obs, targ_proc(obs, next_obs)) == next_obs`` must hold
    :param policy_input_exclude: observation indices the policy network does not see; ``None``:
        ``model_input_exclude`` (give it with an ``obs_preproc`` that drops the root position itself)
    :param policy_obs_preproc: the policy network's input features from raw observations (e.g. the model's
        ``obs_preproc``); ``None``: the observation without ``policy_input_exclude``
    :param description: one line for the task table (docs/tasks.md)
    """

    env_id: str
    reward_fn: RewardFn
    termination_fn: TerminationFn | None = None
    env_kwargs: dict[str, Any] = field(default_factory=dict)
    model_input_exclude: tuple[int, ...] = ()
    obs_preproc: Callable[[th.Tensor], th.Tensor] | None = None
    targ_proc: Callable[[th.Tensor, th.Tensor], th.Tensor] | None = None
    obs_postproc: Callable[[th.Tensor, th.Tensor], th.Tensor] | None = None
    policy_input_exclude: tuple[int, ...] | None = None
    policy_obs_preproc: Callable[[th.Tensor], th.Tensor] | None = None
    description: str = ""

    def __post_init__(self) -> None:
        try:
            self.hooks  # noqa: B018 (validates)
        except ValueError as error:
            raise ValueError(f"TaskSpec {self.env_id!r}: {str(error).removeprefix('ModelHooks: ')}") from None

    @property
    def hooks(self) -> ModelHooks:
        """The networks' observation handling of this task: what a new agent is built with (``POPLIN(model_hooks=)``)."""
        return ModelHooks(
            model_input_exclude=self.model_input_exclude,
            obs_preproc=self.obs_preproc,
            targ_proc=self.targ_proc,
            obs_postproc=self.obs_postproc,
            policy_input_exclude=self.policy_input_exclude,
            policy_obs_preproc=self.policy_obs_preproc,
        )


# the fields of ModelHooks (and of TaskSpec that make them): the dynamics model's hooks and the policy network's inputs
HOOK_KEYS = ("model_input_exclude", "obs_preproc", "targ_proc", "obs_postproc", "policy_input_exclude", "policy_obs_preproc")


_REGISTRY: dict[str, TaskSpec] = {}


def squared_norm(action: th.Tensor) -> th.Tensor:
    """:return: ``sum(action^2)`` over the last dimension (the control cost of most tasks, before its weight)"""
    return (action**2).sum(dim=-1)


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


def check_observation_space(space: gym.Space, env_id: str | None = None) -> None:
    """
    Check that observations are flat vectors, the only kind the dynamics model and the task functions handle.

    :param space: the env's observation space
    :param env_id: the env's id, named in the error message when given
    :raises ValueError: when ``space`` is not a :class:`gymnasium.spaces.Box` with a 1-D shape
    """
    if isinstance(space, gym.spaces.Box) and len(space.shape) == 1:
        return
    name = f"{env_id!r}" if env_id is not None else "This env"
    problem = f"has shape {space.shape}" if isinstance(space, gym.spaces.Box) else f"is a {type(space).__name__}"
    raise ValueError(
        f"{name} has the observation space {space}, which {problem}: the dynamics model and the task's reward and "
        "termination functions need a flat 1-D Box observation space. Wrap the env with "
        "gymnasium.wrappers.FlattenObservation (or a wrapper of your own that returns a 1-D float vector) and write "
        "the reward_fn / termination_fn for the flattened layout."
    )


def make_task(env_id: str, observation_space: gym.Space | None = None) -> TaskSpec:
    """
    Look up the :class:`TaskSpec` of a gymnasium id.

    :param env_id: the gymnasium id, e.g. ``"Pendulum-v1"``
    :param observation_space: when given, also checked with :func:`check_observation_space`
    :return: the registered spec
    """
    if observation_space is not None:
        check_observation_space(observation_space, env_id)
    try:
        return _REGISTRY[env_id]
    except KeyError:
        raise ValueError(
            f"No task is registered for {env_id!r}. Registered tasks: {registered_tasks()}. "
            "Pass reward_fn= (and termination_fn=) to POPLIN, or register a TaskSpec with "
            "sb3_poplin.tasks.register_task."
        ) from None


# Built-in tasks register themselves on import.
from sb3_poplin.tasks import classic, mbbl, mujoco, paper, pets_arm  # noqa: E402, F401
from sb3_poplin.tasks.env_util import (  # noqa: E402
    check_spaces,
    env_id,
    make_env,
    max_episode_steps,
    resolve_task,
    task_env_kwargs,
    task_hooks,
)

__all__ = [
    "ModelHooks",
    "RewardFn",
    "TaskSpec",
    "TerminationFn",
    "check_observation_space",
    "check_spaces",
    "env_id",
    "has_task",
    "make_env",
    "make_task",
    "max_episode_steps",
    "register_task",
    "registered_tasks",
    "resolve_task",
    "squared_norm",
    "task_env_kwargs",
    "task_hooks",
]
