"""
What every part of the package needs to know about an env besides its task: its gymnasium id, its episode length,
whether the planner can handle its spaces, and how to make it with the env kwargs its task's reward assumes.
Used by the algorithm, the callbacks and the rl-zoo3 front end alike.
"""

from __future__ import annotations

import warnings
from typing import Any

import gymnasium as gym
import numpy as np
from gymnasium import spaces
from stable_baselines3.common.type_aliases import GymEnv
from stable_baselines3.common.vec_env import VecEnv

from sb3_poplin.tasks import RewardFn, TerminationFn, check_observation_space, has_task, make_task
from sb3_poplin.tasks.hooks import ModelHooks


def _spec(env: GymEnv) -> Any:
    try:
        return env.get_attr("spec", [0])[0] if isinstance(env, VecEnv) else env.unwrapped.spec
    except (AttributeError, IndexError):
        return None


def env_id(env: GymEnv | str | None) -> str | None:
    """The gymnasium id behind an env id, Env or VecEnv (None when it cannot be told)."""
    if env is None or isinstance(env, str):
        return env
    spec = _spec(env)
    return None if spec is None else spec.id


def max_episode_steps(env: GymEnv | None) -> int | None:
    """The episode length of an Env or VecEnv's time limit (None when it has none or it cannot be told)."""
    spec = None if env is None else _spec(env)
    return None if spec is None else spec.max_episode_steps


def check_spaces(env: GymEnv | None) -> None:
    """
    Reject, with the reason and the fix, the envs the planner cannot handle: it needs a Box action space with finite
    bounds (of any shape: it plans the flattened actions) and a flat Box observation space.

    :raises ValueError: naming the problem and the fix
    """
    if env is None:
        return
    action_space = env.action_space
    if not isinstance(action_space, spaces.Box):
        raise ValueError(
            f"POPLIN plans continuous actions and needs a Box action space, got {action_space}. "
            "Use a continuous-action environment (e.g. Pendulum-v1), or a model-free SB3 algorithm "
            "such as DQN or PPO for discrete actions."
        )
    if not (np.all(np.isfinite(action_space.low)) and np.all(np.isfinite(action_space.high))):
        raise ValueError(
            f"POPLIN needs finite action bounds, got low={action_space.low}, high={action_space.high}. "
            "Wrap the env with gymnasium.wrappers.ClipAction or RescaleAction to bound it."
        )
    check_observation_space(env.observation_space, env_id(env))


def task_env_kwargs(env_id: str, env_kwargs: dict[str, Any] | None = None) -> dict[str, Any]:
    """
    Add the env kwargs that the task's reward function needs (``make_task(env_id).env_kwargs``).

    :param env_id: gymnasium id
    :param env_kwargs: the env kwargs of a config or command line; they win over the task's (with a warning where
        they contradict it)
    :return: a new dict: ``env_kwargs`` plus the task's kwargs it lacks
    """
    merged = dict(env_kwargs or {})
    if not has_task(env_id):
        return merged
    for key, value in make_task(env_id).env_kwargs.items():
        if key not in merged:
            merged[key] = value
        elif merged[key] != value:
            warnings.warn(
                f"env_kwargs sets {key}={merged[key]!r} for {env_id}, but the task's reward function assumes "
                f"{key}={value!r}: the planner's reward will be wrong unless a reward_fn is given.",
                stacklevel=2,
            )
    return merged


def make_env(env_id: str, **env_kwargs: Any) -> gym.Env:
    """``gym.make`` with the env kwargs the task's reward function needs (see :func:`task_env_kwargs`)."""
    return gym.make(env_id, **task_env_kwargs(env_id, env_kwargs))


def resolve_task(
    task_id: str | None,
    reward_fn: RewardFn | None,
    termination_fn: TerminationFn | None,
    learned_reward: bool | None,
) -> tuple[RewardFn | None, TerminationFn | None, bool]:
    """
    What the planner uses for an env: the user's functions win over the registered task's.

    :param task_id: the env's gymnasium id (None when unknown)
    :param reward_fn: the user's reward function, or None
    :param termination_fn: the user's termination function, or None
    :param learned_reward: the model learns the reward; None: only when no reward function is known
    :return: the planner's reward function (None when the reward is learned), its termination function, and whether
        the reward is learned
    """
    task = make_task(task_id) if task_id is not None and has_task(task_id) else None
    reward_fn = reward_fn or (task.reward_fn if task else None)
    termination_fn = termination_fn or (task.termination_fn if task else None)
    if learned_reward is None:
        learned_reward = reward_fn is None
    if learned_reward and termination_fn is None and task is None:
        warnings.warn(
            f"No reward or termination function is known for {task_id!r}: the model learns the reward and the planner "
            "assumes episodes never terminate. Pass termination_fn= (or register a TaskSpec with "
            "sb3_poplin.tasks.register_task) if this env can terminate.",
            stacklevel=4,
        )
    return (None if learned_reward else reward_fn), termination_fn, learned_reward


def task_hooks(task_id: str | None) -> ModelHooks:
    """
    :param task_id: the env's gymnasium id (None when unknown)
    :return: the registered task's hooks (:attr:`TaskSpec.hooks`); no hooks (raw observations, delta targets) for an
        env without a task
    """
    return make_task(task_id).hooks if task_id is not None and has_task(task_id) else ModelHooks()
