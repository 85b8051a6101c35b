"""
Tasks of the PETS 7-DoF arm (:mod:`sb3_poplin.envs.pets_arm`): ``sb3_poplin/PETSReacher3D-v0`` and
``sb3_poplin/PETSPusher-v0``.

The arm's link geometry lives here (the env module builds its MuJoCo model from these numbers), so the reward's
forward kinematics and the simulated arm cannot drift apart; ``tests/test_tasks.py`` checks the kinematics below
against MuJoCo's and every spec against ``env.step``. This module does not import MuJoCo.
"""

from __future__ import annotations

import torch as th

from sb3_poplin.tasks import TaskSpec, register_task, squared_norm

# ------------------------------------------------------------------------------------------------------------ the arm
# A PR2-like arm: shoulder pan (about z), shoulder lift (about y), upper-arm roll (about x), elbow flex (y),
# forearm roll (x), wrist flex (y), wrist roll (x); x points along the arm when every angle is 0.
ARM_JOINTS = 7
# PETS's reacher geometry: the shoulder's position, the lift axis 0.1 m out along the pan link, upper arm 0.4 m,
# forearm 0.321 m, and the end effector 0.16828 m beyond the wrist flex axis, on the wrist roll axis.
REACHER_SHOULDER = (0.0, -0.188, 0.0)
SHOULDER_OFFSET = 0.1
UPPER_ARM_LENGTH = 0.4
FOREARM_LENGTH = 0.321
REACHER_HAND_LENGTH = 0.16828

# sb3_poplin/PETSReacher3D-v0: obs = [qpos (10): 7 arm angles, goal x, y, z; arm qvel (7)] (PETS's layout: the goal
# is a body on three slide joints, so it sits in qpos), action = 7 torques in [-20, 20]
REACHER_GOAL = slice(7, 10)
REACHER_CTRL_COST = 0.01
REACHER_GOAL_MEAN = (0.0, 0.25, 0.0)
REACHER_GOAL_STD = 0.1


def _turn(first: th.Tensor, second: th.Tensor, angle: th.Tensor) -> tuple[th.Tensor, th.Tensor]:
    """
    Turn a frame about one of its own axes: with ``(first, second)`` two of its axes (world coordinates, ``[..., 3]``)
    in the right-handed order of the rotation axis (x: y, z; y: z, x; z: x, y), return them after the turn.

    :param first: the axis that turns towards ``second``
    :param second: the other one
    :param angle: the turn (radians) ``[...]``
    :return: the two axes after the turn
    """
    cos, sin = th.cos(angle)[..., None], th.sin(angle)[..., None]
    return cos * first + sin * second, cos * second - sin * first


def arm_point(angles: th.Tensor, shoulder: tuple[float, float, float], hand_length: float) -> th.Tensor:
    """
    Forward kinematics of the arm: the world position of a point on the wrist roll axis.

    :param angles: the 7 joint angles ``[..., 7]`` (the last, wrist roll, does not move a point on its own axis)
    :param shoulder: the shoulder's world position
    :param hand_length: the point's distance beyond the wrist flex axis
    :return: the point ``[..., 3]``
    """
    batch = angles.shape[:-1]
    x_axis = angles.new_zeros(*batch, 3)
    x_axis[..., 0] = 1.0
    y_axis = angles.new_zeros(*batch, 3)
    y_axis[..., 1] = 1.0
    z_axis = angles.new_zeros(*batch, 3)
    z_axis[..., 2] = 1.0
    point = angles.new_tensor(shoulder).expand(*batch, 3)
    x_axis, y_axis = _turn(x_axis, y_axis, angles[..., 0])  # shoulder pan, about z
    point = point + SHOULDER_OFFSET * x_axis
    z_axis, x_axis = _turn(z_axis, x_axis, angles[..., 1])  # shoulder lift, about y
    y_axis, z_axis = _turn(y_axis, z_axis, angles[..., 2])  # upper arm roll, about x
    point = point + UPPER_ARM_LENGTH * x_axis
    z_axis, x_axis = _turn(z_axis, x_axis, angles[..., 3])  # elbow flex, about y
    y_axis, z_axis = _turn(y_axis, z_axis, angles[..., 4])  # forearm roll, about x
    point = point + FOREARM_LENGTH * x_axis
    z_axis, x_axis = _turn(z_axis, x_axis, angles[..., 5])  # wrist flex, about y
    return point + hand_length * x_axis


def reacher3d_end_effector(obs: th.Tensor) -> th.Tensor:
    """:return: the Reacher3D end effector ``[..., 3]`` from the joint angles ``obs[..., :7]``"""
    return arm_point(obs[..., :ARM_JOINTS], REACHER_SHOULDER, REACHER_HAND_LENGTH)


def reacher3d_reward(obs: th.Tensor, action: th.Tensor, next_obs: th.Tensor) -> th.Tensor:
    """PETS Reacher3D: ``-|EE(s') - goal|^2 - 0.01 |a|^2``, with the goal read from ``s'[7:10]``."""
    distance = ((reacher3d_end_effector(next_obs) - next_obs[..., REACHER_GOAL]) ** 2).sum(dim=-1)
    return -distance - REACHER_CTRL_COST * squared_norm(action)


# sb3_poplin/PETSPusher-v0: obs = [arm qpos (7), arm qvel (7), tip (3), object (3)], action = 7 torques in [-2, 2]
PUSHER_TIP = slice(14, 17)
PUSHER_OBJECT = slice(17, 20)
# The goal body's position (fixed: PETS puts the goal slides at 0 on every reset) and the object's start, which is
# OBJECT_BASE + (PUSHER_OBJECT_START + N(0, 0.025^2) on each of x and y)
PUSHER_GOAL = (0.45, -0.05, -0.323)
PUSHER_OBJECT_BASE = (0.45, -0.05, -0.275)
PUSHER_OBJECT_START = (0.15, -0.25)  # (x, y) offsets: PETS draws (y, x) = (-0.25, 0.15) + noise for its (y, x) slides
PUSHER_OBJECT_START_STD = 0.025
# The tip is the point between the two fingertips, 0.1 m beyond the wrist flex axis (the centre of mass of the
# fingertip body, which is what old gym's get_body_com returned and PETS observed).
PUSHER_SHOULDER = (0.0, -0.6, 0.0)
PUSHER_TIP_LENGTH = 0.1
PUSHER_GOAL_WEIGHT = 1.25
PUSHER_NEAR_WEIGHT = 0.5
PUSHER_CTRL_COST = 0.1


def pusher_reward(obs: th.Tensor, action: th.Tensor, next_obs: th.Tensor) -> th.Tensor:
    """
    PETS Pusher: ``-1.25 |obj - goal|_1 - 0.5 |obj - tip|_1 - 0.1 |a|^2`` on the positions *before* the step
    (``obs``), as PETS's env computes it; the goal is fixed at :data:`PUSHER_GOAL`.
    """
    obj, tip = obs[..., PUSHER_OBJECT], obs[..., PUSHER_TIP]
    to_goal = (obj - obj.new_tensor(PUSHER_GOAL)).abs().sum(dim=-1)
    to_tip = (obj - tip).abs().sum(dim=-1)
    return -PUSHER_GOAL_WEIGHT * to_goal - PUSHER_NEAR_WEIGHT * to_tip - PUSHER_CTRL_COST * squared_norm(action)


for _spec in (
    TaskSpec(
        env_id="sb3_poplin/PETSReacher3D-v0",
        reward_fn=reacher3d_reward,
        description="obs = [7 angles, goal (3), 7 velocities]; EE by forward kinematics; never terminates",
    ),
    TaskSpec(
        env_id="sb3_poplin/PETSPusher-v0",
        reward_fn=pusher_reward,
        description="obs = [7 angles, 7 velocities, tip (3), object (3)]; reward on the pre-step obs; never terminates",
    ),
):
    register_task(_spec)
