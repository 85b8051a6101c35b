"""
Is the model or the planner what limits an agent? An MPC episode with a trained agent, and the open-loop k-step error
of its learned ensemble on that episode: from every ``stride``-th state, the ensemble (expectation propagation, as
the planner uses it) predicts the next ``horizon`` states under the executed actions; per prediction step k the
report gives the state RMSE in units of each dimension's standard deviation over the episode, and the error of the
predicted k-step return (what CEM ranks candidates by) against the real one.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import gymnasium as gym
import numpy as np
import torch as th

from sb3_poplin.planning import MPCController


@dataclass
class Episode:
    """One MPC episode: observations ``[T + 1, o]``, env-unit actions ``[T, a]``, rewards ``[T]`` and per step the
    plan's model-predicted return (the final elites' mean)."""

    obs: np.ndarray
    actions: np.ndarray
    rewards: np.ndarray
    planned_returns: np.ndarray = field(default_factory=lambda: np.zeros(0))

    @property
    def total(self) -> float:
        return float(self.rewards.sum())


def mpc_episode(controller: MPCController, env: gym.Env, steps: int, seed: int) -> Episode:
    """
    At most ``steps`` MPC steps from ``env.reset(seed=seed)``, each env's plan warm-started from the previous one.

    :param controller: an agent's ``mpc``, or a :func:`sb3_poplin.variants.replanner` of it
    """
    obs, _ = env.reset(seed=seed)
    observations, actions, rewards, planned = [obs], [], [], []
    state = None
    for t in range(steps):
        obs_tensor = th.as_tensor(obs, dtype=th.float32, device=controller.device).unsqueeze(0)
        step = controller.step(obs_tensor, state, episode_start=np.array([t == 0]))
        state = step.state
        planned.append(float(step.plan.elite_return[0]))
        obs, reward, terminated, truncated, _ = env.step(step.actions[0])
        observations.append(obs)
        actions.append(step.actions[0])
        rewards.append(float(reward))
        if terminated or truncated:
            break
    return Episode(np.array(observations), np.array(actions), np.array(rewards), np.array(planned))


@th.no_grad()
def model_error(agent: Any, episode: Episode, stride: int = 5, horizon: int | None = None) -> dict[str, list[float]]:
    """
    Open-loop multi-step prediction error of an agent's ensemble on an episode.

    :param agent: a POPLIN agent (its ensemble and its planner's reward: the task's, or the learned one)
    :param episode: the episode
    :param stride: start a prediction at every ``stride``-th state
    :param horizon: prediction steps; ``None``: the agent's planning horizon
    :return: per prediction step k = 1..H: ``state_rmse`` (normalised), ``return_abs_error`` (mean absolute error of
        the predicted k-step return) and ``real_return_abs`` (the mean absolute real k-step return, for scale)
    """
    planner, dynamics, device = agent.planner, agent.policy.dynamics, agent.device
    horizon = agent.settings.horizon if horizon is None else horizon
    obs = th.as_tensor(episode.obs, dtype=th.float32, device=device)
    actions = th.as_tensor(episode.actions, dtype=th.float32, device=device)
    rewards = th.as_tensor(episode.rewards, dtype=th.float32, device=device)
    if len(actions) < horizon:
        raise ValueError(f"The episode has {len(actions)} steps, fewer than the {horizon} prediction steps.")
    starts = th.arange(0, len(actions) - horizon + 1, stride, device=device)
    scaled = th.as_tensor(agent.policy.scale_action(episode.actions), dtype=th.float32, device=device)
    state_std = obs.std(dim=0).clamp(min=1e-6)
    states = obs[starts].unsqueeze(1)  # [N, 1, o]
    predicted_return = th.zeros(len(starts), device=device)
    real_return = th.zeros(len(starts), device=device)
    rmse, return_error, return_scale = [], [], []
    for k in range(horizon):
        next_states, model_reward = dynamics.propagate(states, scaled[starts + k].unsqueeze(1), "expectation")
        if planner.reward_fn is None:
            assert model_reward is not None
            predicted_return += model_reward[:, 0]
        else:
            predicted_return += planner.reward_fn(states[:, 0], actions[starts + k], next_states[:, 0])
        real_return += rewards[starts + k]
        states = next_states
        error = (states[:, 0] - obs[starts + k + 1]) / state_std
        rmse.append(float(error.pow(2).mean().sqrt()))
        return_error.append(float((predicted_return - real_return).abs().mean()))
        return_scale.append(float(real_return.abs().mean()))
    return {"state_rmse": rmse, "return_abs_error": return_error, "real_return_abs": return_scale}
