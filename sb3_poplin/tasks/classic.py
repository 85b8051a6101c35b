"""Classic-control tasks (gymnasium ``classic_control``)."""

from __future__ import annotations

import torch as th

from sb3_poplin.tasks import TaskSpec, register_task

# Pendulum-v1: obs = [cos(theta), sin(theta), theta_dot], action = torque in [-2, 2]
PENDULUM_COS, PENDULUM_SIN, PENDULUM_THETA_DOT = 0, 1, 2
PENDULUM_MAX_TORQUE = 2.0


def pendulum_reward(obs: th.Tensor, action: th.Tensor, next_obs: th.Tensor) -> th.Tensor:
    """
    Pendulum-v1 reward: ``-(theta^2 + 0.1 theta_dot^2 + 0.001 u^2)`` on the state *before* the step,
    with theta normalised to [-pi, pi) and u clipped to the torque limit.
    """
    theta = th.atan2(obs[..., PENDULUM_SIN], obs[..., PENDULUM_COS])
    torque = action[..., 0].clamp(-PENDULUM_MAX_TORQUE, PENDULUM_MAX_TORQUE)
    return -(theta**2 + 0.1 * obs[..., PENDULUM_THETA_DOT] ** 2 + 0.001 * torque**2)


register_task(
    TaskSpec(
        env_id="Pendulum-v1",
        reward_fn=pendulum_reward,
        termination_fn=None,
        description="reward from the pre-step obs (theta = atan2(sin, cos)); never terminates",
    )
)
