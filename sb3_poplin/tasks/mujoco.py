"""Gymnasium v5 MuJoCo tasks."""

from __future__ import annotations

import torch as th

from sb3_poplin.tasks import TaskSpec, register_task

# InvertedPendulum-v5: obs = [cart x, pole angle, cart velocity, pole angular velocity], action in [-3, 3]
INVERTED_PENDULUM_ANGLE = 1
INVERTED_PENDULUM_MAX_ANGLE = 0.2


def inverted_pendulum_termination(obs: th.Tensor, action: th.Tensor, next_obs: th.Tensor) -> th.Tensor:
    """InvertedPendulum-v5 terminates when the next obs is not finite or ``|pole angle| > 0.2``."""
    not_finite = ~th.isfinite(next_obs).all(dim=-1)
    return not_finite | (next_obs[..., INVERTED_PENDULUM_ANGLE].abs() > INVERTED_PENDULUM_MAX_ANGLE)


def inverted_pendulum_reward(obs: th.Tensor, action: th.Tensor, next_obs: th.Tensor) -> th.Tensor:
    """InvertedPendulum-v5 pays 1 per step that does not terminate (0 on the terminating step)."""
    return (~inverted_pendulum_termination(obs, action, next_obs)).to(next_obs.dtype)


register_task(
    TaskSpec(
        env_id="InvertedPendulum-v5",
        reward_fn=inverted_pendulum_reward,
        termination_fn=inverted_pendulum_termination,
        description="reward 1 while |angle| <= 0.2; terminates when |next angle| > 0.2 or non-finite",
    )
)
