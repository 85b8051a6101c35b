"""
The PETS paper's 7-DoF arm tasks (Chua et al. 2018), which the POPLIN paper calls Reacher3D and Pusher.

Both arms are built at run time from the arm of gymnasium's legacy ``pusher.xml`` (the PR2-like arm that PETS's
own ``pusher.xml`` also uses) with :class:`mujoco.MjSpec` edits, so no asset is copied into this package:

* :class:`PETSReacher3DEnv`: the object, goal and table removed; the shoulder moved to PETS's reacher position;
  PETS's reacher joint ranges, damping and +-20 motors; RK4; a goal body on three slide joints; an end-effector
  site 0.16828 m beyond the wrist flex axis. Link lengths: :mod:`sb3_poplin.tasks.pets_arm`.
* :class:`PETSPusherEnv`: gymnasium's ``pusher.xml`` (which equals PETS's but for the shoulder pan's upper limit,
  set here to PETS's 2.0) plus a site at the tip, PETS's frame skip (4), reset and reward.

Positions in the observations (end effector, tip, object) are MuJoCo's forward kinematics of the state the
observation reports (``mj_kinematics`` after the step); MuJoCo's own values after ``mj_step`` are those of the
start of the last substep, which PETS (and gymnasium's Pusher) observed.
"""

from __future__ import annotations

from typing import Any

import mujoco
import numpy as np
from gymnasium import utils
from gymnasium.envs.mujoco.mujoco_env import MujocoEnv, expand_model_path
from gymnasium.spaces import Box
from numpy.typing import NDArray

from sb3_poplin.tasks.pets_arm import (
    ARM_JOINTS,
    FOREARM_LENGTH,
    PUSHER_CTRL_COST,
    PUSHER_GOAL,
    PUSHER_GOAL_WEIGHT,
    PUSHER_NEAR_WEIGHT,
    PUSHER_OBJECT_START,
    PUSHER_OBJECT_START_STD,
    PUSHER_TIP_LENGTH,
    REACHER_CTRL_COST,
    REACHER_GOAL_MEAN,
    REACHER_GOAL_STD,
    REACHER_HAND_LENGTH,
    REACHER_SHOULDER,
    SHOULDER_OFFSET,
    UPPER_ARM_LENGTH,
)

# MujocoEnv.step's declared return type
StepResult = tuple[NDArray[np.float64], np.float64, bool, bool, dict[str, np.float64]]

ARM_ASSET = "pusher.xml"  # gymnasium's legacy Pusher model (Pusher-v4 and earlier)
JOINT_NAMES = (
    "r_shoulder_pan_joint",
    "r_shoulder_lift_joint",
    "r_upper_arm_roll_joint",
    "r_elbow_flex_joint",
    "r_forearm_roll_joint",
    "r_wrist_flex_joint",
    "r_wrist_roll_joint",
)
# PETS's reacher3d joints: (range or None for unlimited, damping); the arm's other joint settings are the asset's
REACHER_JOINTS: dict[str, tuple[tuple[float, float] | None, float]] = {
    "r_shoulder_pan_joint": ((-2.2854, 1.714602), 10.0),
    "r_shoulder_lift_joint": ((-0.5236, 1.3963), 10.0),
    "r_upper_arm_roll_joint": ((-3.9, 0.8), 0.1),
    "r_elbow_flex_joint": ((-2.3213, 0.0), 1.0),
    "r_forearm_roll_joint": (None, 0.1),
    "r_wrist_flex_joint": ((-2.094, 0.0), 0.1),
    "r_wrist_roll_joint": (None, 0.1),
}
REACHER_MAX_TORQUE = 20.0
# PETS's viewer settings
REACHER_CAMERA = {"trackbodyid": 1, "distance": 2.5, "elevation": -30.0, "azimuth": 270.0}
PUSHER_CAMERA = {"trackbodyid": -1, "distance": 4.0}
PUSHER_SHOULDER_PAN_RANGE = (-2.2854, 2.0)


def _check_arm(spec: mujoco.MjSpec) -> None:
    """
    Check that the asset's arm has the link offsets the reward's kinematics assume.

    :param spec: the loaded asset
    :raises ValueError: when the installed gymnasium ships a different arm
    """
    offsets = {
        "r_shoulder_lift_link": (SHOULDER_OFFSET, 0.0, 0.0),
        "r_elbow_flex_link": (UPPER_ARM_LENGTH, 0.0, 0.0),
        "r_wrist_flex_link": (FOREARM_LENGTH, 0.0, 0.0),
    }
    for body, expected in offsets.items():
        if not np.allclose(spec.body(body).pos, expected):
            raise ValueError(
                f"gymnasium's {ARM_ASSET} has {body} at {spec.body(body).pos}, not {expected}: this gymnasium version "
                "ships another arm than the one sb3_poplin's PETS tasks are built from (gymnasium 1.x)."
            )


class PETSReacher3DEnv(MujocoEnv, utils.EzPickle):
    """
    PETS Reacher3D: move the 7-DoF arm's end effector to a 3-D goal drawn per episode; no gravity.

    Observation (17): ``[qpos (10): 7 arm angles, goal x, y, z; arm joint velocities (7)]``, PETS's layout (the
    goal is a body on three slide joints). Action: 7 joint torques in [-20, 20]. Reward on the state after the
    step: ``-|EE - goal|^2 - 0.01 |a|^2``, with EE the end-effector site (equal to
    :func:`sb3_poplin.tasks.pets_arm.reacher3d_end_effector` of the angles). Reset: the arm at rest with every
    angle 0, the goal ``(0, 0.25, 0) + N(0, 0.1^2 I)``. Never terminates; 150 steps of 0.02 s.

    :param frame_skip: MuJoCo steps (0.01 s each) per env step
    :param kwargs: passed to :class:`gymnasium.envs.mujoco.mujoco_env.MujocoEnv` (e.g. ``render_mode``)
    """

    metadata: dict[str, Any] = {"render_modes": ["human", "rgb_array", "depth_array", "rgbd_tuple"]}  # noqa: RUF012

    def __init__(self, frame_skip: int = 2, **kwargs: Any) -> None:
        utils.EzPickle.__init__(self, frame_skip, **kwargs)
        observation_space = Box(low=-np.inf, high=np.inf, shape=(17,), dtype=np.float64)
        self.metadata = {**self.metadata, "render_fps": int(np.round(1.0 / (0.01 * frame_skip)))}
        kwargs.setdefault("default_camera_config", REACHER_CAMERA)
        super().__init__(ARM_ASSET, frame_skip, observation_space=observation_space, **kwargs)
        self._end_effector = self.model.site("end_effector").id
        self.goal = np.zeros(3)

    def _initialize_simulation(self) -> tuple[mujoco.MjModel, mujoco.MjData]:
        """:return: the reacher arm, built from gymnasium's pusher arm"""
        spec = mujoco.MjSpec.from_file(expand_model_path(self.fullpath))
        _check_arm(spec)
        spec.delete(spec.geom("table"))
        spec.delete(spec.body("object"))
        spec.delete(spec.body("goal"))
        spec.option.integrator = mujoco.mjtIntegrator.mjINT_RK4
        spec.body("r_shoulder_pan_link").pos = REACHER_SHOULDER
        for name, (joint_range, damping) in REACHER_JOINTS.items():
            joint = spec.joint(name)
            joint.damping[0] = damping
            if joint_range is None:
                joint.limited = mujoco.mjtLimited.mjLIMITED_FALSE
            else:
                joint.range = joint_range
        for actuator in spec.actuators:
            actuator.ctrlrange = (-REACHER_MAX_TORQUE, REACHER_MAX_TORQUE)
        spec.body("r_wrist_roll_link").add_site(name="end_effector", pos=(REACHER_HAND_LENGTH, 0.0, 0.0), size=(0.01,))
        target = spec.worldbody.add_body(name="target")
        for axis_name, axis in (("x", (1, 0, 0)), ("y", (0, 1, 0)), ("z", (0, 0, 1))):
            joint = target.add_joint(name=f"target_{axis_name}", type=mujoco.mjtJoint.mjJNT_SLIDE, axis=axis)
            joint.limited = mujoco.mjtLimited.mjLIMITED_FALSE  # the asset's default limits every joint
            joint.armature, joint.damping[0] = 0.0, 0.0
        target.add_geom(
            type=mujoco.mjtGeom.mjGEOM_SPHERE, size=(0.035, 0, 0), rgba=(0.9, 0.2, 0.2, 1), contype=0, conaffinity=0
        )
        model = spec.compile()
        model.vis.global_.offwidth = max(model.vis.global_.offwidth, self.width)
        model.vis.global_.offheight = max(model.vis.global_.offheight, self.height)
        return model, mujoco.MjData(model)

    def end_effector(self) -> NDArray[np.float64]:
        """:return: the end effector's world position for the current ``qpos`` (MuJoCo's kinematics)"""
        mujoco.mj_kinematics(self.model, self.data)
        return self.data.site_xpos[self._end_effector].copy()

    def step(self, action: NDArray[np.float32]) -> StepResult:
        """
        :param action: the seven joint torques (MuJoCo clamps them to [-20, 20])
        :return: observation, reward, terminated (always False), truncated (False), info
        """
        self.do_simulation(action, self.frame_skip)
        observation = self._get_obs()
        distance = float(np.sum((self.end_effector() - self.goal) ** 2))
        ctrl_cost = REACHER_CTRL_COST * float(np.sum(np.square(np.asarray(action, dtype=np.float64))))
        info = {"reward_dist": np.float64(-distance), "reward_ctrl": np.float64(-ctrl_cost)}
        if self.render_mode == "human":
            self.render()
        return observation, np.float64(-distance - ctrl_cost), False, False, info

    def reset_model(self) -> NDArray[np.float64]:
        """:return: the first observation (arm at rest with every angle 0, a new goal)"""
        self.goal = np.asarray(REACHER_GOAL_MEAN) + self.np_random.normal(0.0, REACHER_GOAL_STD, size=3)
        qpos = self.init_qpos.copy()
        qpos[ARM_JOINTS:] = self.goal
        self.set_state(qpos, np.zeros(self.model.nv))
        return self._get_obs()

    def _get_obs(self) -> NDArray[np.float64]:
        """:return: ``[qpos (10), arm qvel (7)]``"""
        return np.concatenate([self.data.qpos, self.data.qvel[:ARM_JOINTS]])


class PETSPusherEnv(MujocoEnv, utils.EzPickle):
    """
    PETS Pusher: push a cylinder to a fixed goal on the table with the 7-DoF arm; no gravity.

    Observation (20): ``[arm angles (7), arm joint velocities (7), tip (3), object (3)]``; the goal is not observed
    (it never moves: :data:`sb3_poplin.tasks.pets_arm.PUSHER_GOAL`). Action: 7 joint torques in [-2, 2]. Reward on
    the positions *before* the step (PETS's order): ``-1.25 |obj - goal|_1 - 0.5 |obj - tip|_1 - 0.1 |a|^2``.
    Reset (PETS's): the arm at angle 0 with joint velocities uniform in +-0.005, the object's (x, y) offsets
    ``(0.15, -0.25) + N(0, 0.025^2)`` each, at rest. Never terminates; 150 steps of 0.04 s.

    :param frame_skip: MuJoCo steps (0.01 s each) per env step
    :param kwargs: passed to :class:`gymnasium.envs.mujoco.mujoco_env.MujocoEnv` (e.g. ``render_mode``)
    """

    metadata: dict[str, Any] = {"render_modes": ["human", "rgb_array", "depth_array", "rgbd_tuple"]}  # noqa: RUF012

    def __init__(self, frame_skip: int = 4, **kwargs: Any) -> None:
        utils.EzPickle.__init__(self, frame_skip, **kwargs)
        observation_space = Box(low=-np.inf, high=np.inf, shape=(20,), dtype=np.float64)
        self.metadata = {**self.metadata, "render_fps": int(np.round(1.0 / (0.01 * frame_skip)))}
        kwargs.setdefault("default_camera_config", PUSHER_CAMERA)
        super().__init__(ARM_ASSET, frame_skip, observation_space=observation_space, **kwargs)
        self._tip = self.model.site("tip").id
        self._object = self.model.body("object").id

    def _initialize_simulation(self) -> tuple[mujoco.MjModel, mujoco.MjData]:
        """:return: gymnasium's pusher model with PETS's shoulder pan range and a site at the tip"""
        spec = mujoco.MjSpec.from_file(expand_model_path(self.fullpath))
        _check_arm(spec)
        spec.joint("r_shoulder_pan_joint").range = PUSHER_SHOULDER_PAN_RANGE
        spec.body("tips_arm").add_site(name="tip", pos=(PUSHER_TIP_LENGTH, 0.0, 0.0), size=(0.01,))
        model = spec.compile()
        model.vis.global_.offwidth = max(model.vis.global_.offwidth, self.width)
        model.vis.global_.offheight = max(model.vis.global_.offheight, self.height)
        return model, mujoco.MjData(model)

    def positions(self) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """:return: the tip and the object's world positions for the current ``qpos`` (MuJoCo's kinematics)"""
        mujoco.mj_kinematics(self.model, self.data)
        return self.data.site_xpos[self._tip].copy(), self.data.xpos[self._object].copy()

    def step(self, action: NDArray[np.float32]) -> StepResult:
        """
        :param action: the seven joint torques (MuJoCo clamps them to [-2, 2])
        :return: observation, reward (on the state before the step), terminated (always False), truncated, info
        """
        tip, obj = self.positions()
        reward_dist = -float(np.sum(np.abs(obj - np.asarray(PUSHER_GOAL))))
        reward_near = -float(np.sum(np.abs(obj - tip)))
        reward_ctrl = -float(np.sum(np.square(np.asarray(action, dtype=np.float64))))
        reward = PUSHER_GOAL_WEIGHT * reward_dist + PUSHER_NEAR_WEIGHT * reward_near + PUSHER_CTRL_COST * reward_ctrl
        self.do_simulation(action, self.frame_skip)
        observation = self._get_obs()
        info = {
            "reward_dist": np.float64(reward_dist),
            "reward_near": np.float64(reward_near),
            "reward_ctrl": np.float64(reward_ctrl),
        }
        if self.render_mode == "human":
            self.render()
        return observation, np.float64(reward), False, False, info

    def reset_model(self) -> NDArray[np.float64]:
        """:return: the first observation (PETS's reset)"""
        qpos = self.init_qpos.copy()
        start = np.asarray(PUSHER_OBJECT_START) + self.np_random.normal(0.0, PUSHER_OBJECT_START_STD, size=2)
        qpos[-4:-2] = start[1], start[0]  # the slides are (y, x)
        qpos[-2:] = 0.0  # the goal's slides
        qvel = self.init_qvel + self.np_random.uniform(low=-0.005, high=0.005, size=self.model.nv)
        qvel[-4:] = 0.0
        self.set_state(qpos, qvel)
        return self._get_obs()

    def _get_obs(self) -> NDArray[np.float64]:
        """:return: ``[arm qpos (7), arm qvel (7), tip (3), object (3)]``"""
        tip, obj = self.positions()
        return np.concatenate([self.data.qpos[:ARM_JOINTS], self.data.qvel[:ARM_JOINTS], tip, obj])
