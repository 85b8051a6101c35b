"""
Tasks for the POPLIN / PETS papers' extra environments (:mod:`sb3_poplin.envs`, ``sb3_poplin/`` ids).

The constants here mirror the env classes (``tests/test_tasks.py`` checks every spec against ``env.step``).
This module does not import the MuJoCo-based env classes (they import their shaping constants from here), so
importing :mod:`sb3_poplin` does not import MuJoCo.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch as th

from sb3_poplin.envs.acrobot_swingup import ACROBOT_COS1, ACROBOT_COS2, ACROBOT_SIN1, ACROBOT_SIN2
from sb3_poplin.envs.cartpole_swingup import CARTPOLE_COS, CARTPOLE_X, CARTPOLE_X_COST
from sb3_poplin.tasks import TaskSpec, register_task, squared_norm


# sb3_poplin/PETSCheetah-v0: obs = [(x' - x) / dt, qpos[1:] (8), qvel (9)]
PETS_CHEETAH_VELOCITY = 0
PETS_CHEETAH_CTRL_COST = 0.1


def pets_cheetah_reward(obs: th.Tensor, action: th.Tensor, next_obs: th.Tensor) -> th.Tensor:
    """PETS Cheetah: ``obs'[0] - 0.1 |a|^2``, the forward velocity being the first observation entry."""
    return next_obs[..., PETS_CHEETAH_VELOCITY] - PETS_CHEETAH_CTRL_COST * squared_norm(action)


# PETS's half-cheetah model (its config's obs_preproc / targ_proc / obs_postproc): the forward velocity obs[0] is not
# a model input but is predicted absolutely; obs[2] (the body angle) enters as its sine and cosine; the rest as deltas
PETS_CHEETAH_ANGLE = 2


def pets_cheetah_obs_preproc(obs: th.Tensor) -> th.Tensor:
    """Model input of PETS Cheetah: ``[obs[1], sin obs[2], cos obs[2], obs[3:]]`` (18 features from 18 entries)."""
    angle = obs[..., PETS_CHEETAH_ANGLE : PETS_CHEETAH_ANGLE + 1]
    return th.cat([obs[..., 1:PETS_CHEETAH_ANGLE], th.sin(angle), th.cos(angle), obs[..., PETS_CHEETAH_ANGLE + 1 :]], dim=-1)


def pets_cheetah_targ_proc(obs: th.Tensor, next_obs: th.Tensor) -> th.Tensor:
    """Model target of PETS Cheetah: ``[next[0], next[1:] - obs[1:]]`` (the velocity absolute, the rest as deltas)."""
    return th.cat([next_obs[..., :1], next_obs[..., 1:] - obs[..., 1:]], dim=-1)


def pets_cheetah_obs_postproc(obs: th.Tensor, prediction: th.Tensor) -> th.Tensor:
    """Next observation of PETS Cheetah from a prediction: ``[pred[0], obs[1:] + pred[1:]]``."""
    return th.cat([prediction[..., :1], obs[..., 1:] + prediction[..., 1:]], dim=-1)


def cartpole_swingup_reward(obs: th.Tensor, action: th.Tensor, next_obs: th.Tensor) -> th.Tensor:
    """Cart-pole swing-up: ``cos(theta') - 0.01 x'^2`` (theta = 0 upright), obs = [x, x_dot, cos, sin, theta_dot]."""
    return next_obs[..., CARTPOLE_COS] - CARTPOLE_X_COST * next_obs[..., CARTPOLE_X] ** 2


def acrobot_swingup_reward(obs: th.Tensor, action: th.Tensor, next_obs: th.Tensor) -> th.Tensor:
    """
    Acrobot swing-up: the tip height ``-(cos q1' + cos(q1' + q2'))`` with ``q1 = q2 = 0`` hanging down,
    from obs = [cos q1, sin q1, cos q2, sin q2, q1_dot, q2_dot].
    """
    cos1, sin1 = next_obs[..., ACROBOT_COS1], next_obs[..., ACROBOT_SIN1]
    cos2, sin2 = next_obs[..., ACROBOT_COS2], next_obs[..., ACROBOT_SIN2]
    return -(cos1 + (cos1 * cos2 - sin1 * sin2))


# sb3_poplin/FixedSwimmer-v0: obs = [qpos[2:] (3), qvel (5), head x velocity]
FIXED_SWIMMER_HEAD_VELOCITY = -1
FIXED_SWIMMER_CTRL_COST = 1e-4


def fixed_swimmer_reward(obs: th.Tensor, action: th.Tensor, next_obs: th.Tensor) -> th.Tensor:
    """Fixed Swimmer: ``obs'[-1] - 1e-4 |a|^2``, the head's x velocity being the last observation entry."""
    return next_obs[..., FIXED_SWIMMER_HEAD_VELOCITY] - FIXED_SWIMMER_CTRL_COST * squared_norm(action)


# No-termination locomotion (Hopper, Walker2d: obs = [x, z, ...]; Ant: obs = [x, y, z, ...]), x kept in obs[0].
SHAPED_HEIGHT_COST = 3.0
SHAPED_CTRL_COST = 0.1
SHAPED_ALIVE_BONUS = 1.0
HOPPER_TARGET_HEIGHT = 1.3
WALKER_TARGET_HEIGHT = 1.3
ANT_TARGET_HEIGHT = 0.57


@dataclass(frozen=True)
class ShapedLocomotionReward:
    """
    The paper's no-termination locomotion reward ``(x' - x) / dt - 3 (z' - z_target)^2 - 0.1 |a|^2 + 1``.

    A small class rather than a closure, so that it pickles.

    :param dt: seconds per env step
    :param z_index: observation index of the root height (x is at index 0)
    :param target_height: ``z_target``
    """

    dt: float
    z_index: int
    target_height: float

    def __call__(self, obs: th.Tensor, action: th.Tensor, next_obs: th.Tensor) -> th.Tensor:
        """
        :param obs: observations before the step ``[B, o]``
        :param action: actions in env units ``[B, a]``
        :param next_obs: observations after the step ``[B, o]``
        :return: rewards ``[B]``
        """
        forward = (next_obs[..., 0] - obs[..., 0]) / self.dt
        height_cost = SHAPED_HEIGHT_COST * (next_obs[..., self.z_index] - self.target_height) ** 2
        return forward - height_cost - SHAPED_CTRL_COST * squared_norm(action) + SHAPED_ALIVE_BONUS


# dt = timestep * frame_skip of the v5 models: Hopper, Walker2d 0.002 * 4, Ant 0.01 * 5
hopper_no_term_reward = ShapedLocomotionReward(dt=0.008, z_index=1, target_height=HOPPER_TARGET_HEIGHT)
walker2d_no_term_reward = ShapedLocomotionReward(dt=0.008, z_index=1, target_height=WALKER_TARGET_HEIGHT)
ant_no_term_reward = ShapedLocomotionReward(dt=0.05, z_index=2, target_height=ANT_TARGET_HEIGHT)


for _spec in (
    TaskSpec(
        env_id="sb3_poplin/PETSCheetah-v0",
        reward_fn=pets_cheetah_reward,
        obs_preproc=pets_cheetah_obs_preproc,
        targ_proc=pets_cheetah_targ_proc,
        obs_postproc=pets_cheetah_obs_postproc,
        description="obs[0] is the forward velocity (x not observed); never terminates; PETS's model hooks",
    ),
    TaskSpec(
        env_id="sb3_poplin/CartPoleSwingUp-v0",
        reward_fn=cartpole_swingup_reward,
        description="obs = [x, x_dot, cos, sin, theta_dot]; never terminates",
    ),
    TaskSpec(
        env_id="sb3_poplin/AcrobotSwingUp-v0",
        reward_fn=acrobot_swingup_reward,
        description="obs = [cos q1, sin q1, cos q2, sin q2, q1_dot, q2_dot]; never terminates",
    ),
    TaskSpec(
        env_id="sb3_poplin/FixedSwimmer-v0",
        reward_fn=fixed_swimmer_reward,
        description="obs[-1] is the head's x velocity; never terminates",
    ),
    TaskSpec(
        env_id="sb3_poplin/HopperNoTerm-v0",
        reward_fn=hopper_no_term_reward,
        model_input_exclude=(0,),
        description="x kept in obs[0], hidden from the model; never terminates",
    ),
    TaskSpec(
        env_id="sb3_poplin/Walker2dNoTerm-v0",
        reward_fn=walker2d_no_term_reward,
        model_input_exclude=(0,),
        description="x kept in obs[0], hidden from the model; never terminates",
    ),
    TaskSpec(
        env_id="sb3_poplin/AntNoTerm-v0",
        reward_fn=ant_no_term_reward,
        model_input_exclude=(0, 1),
        description="x, y kept in obs[0:2], hidden from the model; no contact forces; never terminates",
    ),
):
    register_task(_spec)
