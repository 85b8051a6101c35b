"""
Tasks of the MBBL classic-control envs the POPLIN paper uses (:mod:`sb3_poplin.envs.mbbl_classic`,
:class:`sb3_poplin.envs.mujoco_variants.MBBLInvertedPendulumEnv`).

MBBL computes every reward on the observation *before* the step (``obs`` here, not ``next_obs``) and the action;
none of these envs terminates. ``tests/test_tasks.py`` checks each spec against ``env.step``. This module does not
import MuJoCo.
"""

from __future__ import annotations

import torch as th

from sb3_poplin.envs.acrobot_swingup import ACROBOT_COS1, ACROBOT_COS2, ACROBOT_SIN1, ACROBOT_SIN2
from sb3_poplin.envs.mbbl_classic import (
    CARTPOLE_THETA,
    CARTPOLE_X,
    CARTPOLE_X_COST,
    PENDULUM_COS,
    PENDULUM_MAX_TORQUE,
    PENDULUM_SIN,
    PENDULUM_SIN_COST,
    PENDULUM_THETA_DOT,
    PENDULUM_TORQUE_COST,
    PENDULUM_VELOCITY_COST,
)
from sb3_poplin.tasks import TaskSpec, register_task

# sb3_poplin/MBBLInvertedPendulum-v0: obs = [cart x, pole angle, cart velocity, pole angular velocity]
MBBL_INVERTED_PENDULUM_ANGLE = 1


def mbbl_pendulum_reward(obs: th.Tensor, action: th.Tensor, next_obs: th.Tensor) -> th.Tensor:
    """
    MBBL Pendulum: ``-(cos(theta) + 0.1 |sin(theta)| + 0.1 theta_dot^2 + 0.001 u^2)`` on the pre-step obs
    ``[cos, sin, theta_dot]`` (theta = 0 upright), with the torque ``u = 2 clip(a, -1, 1)``.
    """
    torque = PENDULUM_MAX_TORQUE * action[..., 0].clamp(-1.0, 1.0)
    cost = obs[..., PENDULUM_COS] + PENDULUM_SIN_COST * obs[..., PENDULUM_SIN].abs()
    cost = cost + PENDULUM_VELOCITY_COST * obs[..., PENDULUM_THETA_DOT] ** 2 + PENDULUM_TORQUE_COST * torque**2
    return -cost


def mbbl_inverted_pendulum_reward(obs: th.Tensor, action: th.Tensor, next_obs: th.Tensor) -> th.Tensor:
    """MBBL InvertedPendulum: ``-theta^2``, the pole angle of the pre-step obs."""
    return -(obs[..., MBBL_INVERTED_PENDULUM_ANGLE] ** 2)


def mbbl_acrobot_reward(obs: th.Tensor, action: th.Tensor, next_obs: th.Tensor) -> th.Tensor:
    """MBBL Acrobot: the tip height ``-(cos q1 + cos(q1 + q2))`` of the pre-step obs (q1 = q2 = 0 hangs down)."""
    cos1, sin1 = obs[..., ACROBOT_COS1], obs[..., ACROBOT_SIN1]
    cos2, sin2 = obs[..., ACROBOT_COS2], obs[..., ACROBOT_SIN2]
    return -(cos1 + (cos1 * cos2 - sin1 * sin2))


def mbbl_cartpole_reward(obs: th.Tensor, action: th.Tensor, next_obs: th.Tensor) -> th.Tensor:
    """MBBL Cartpole: ``cos(theta) - 0.01 x^2`` on the pre-step obs ``[x, x_dot, theta, theta_dot]`` (0 upright)."""
    return th.cos(obs[..., CARTPOLE_THETA]) - CARTPOLE_X_COST * obs[..., CARTPOLE_X] ** 2


for _spec in (
    TaskSpec(
        env_id="sb3_poplin/MBBLPendulum-v0",
        reward_fn=mbbl_pendulum_reward,
        description="obs = [cos, sin, theta_dot]; reward on the pre-step obs, best hanging down; never terminates",
    ),
    TaskSpec(
        env_id="sb3_poplin/MBBLInvertedPendulum-v0",
        reward_fn=mbbl_inverted_pendulum_reward,
        description="InvertedPendulum-v5's obs; reward -theta^2 on the pre-step obs; never terminates",
    ),
    TaskSpec(
        env_id="sb3_poplin/MBBLAcrobot-v0",
        reward_fn=mbbl_acrobot_reward,
        description="obs = [cos q1, sin q1, cos q2, sin q2, q1_dot, q2_dot]; tip height before the step",
    ),
    TaskSpec(
        env_id="sb3_poplin/MBBLCartpole-v0",
        reward_fn=mbbl_cartpole_reward,
        description="obs = [x, x_dot, theta, theta_dot]; reward on the pre-step obs; never terminates",
    ),
):
    register_task(_spec)
