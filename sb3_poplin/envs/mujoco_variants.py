"""
MuJoCo tasks of the POPLIN / PETS papers, as subclasses of the gymnasium v5 environments (same models).

* :class:`PETSCheetahEnv`: HalfCheetah whose first observation entry is the forward velocity.
* :class:`FixedSwimmerEnv`: Swimmer paid the velocity of its head rather than of its body frame.
* :class:`HopperNoTermEnv`, :class:`Walker2dNoTermEnv`, :class:`AntNoTermEnv`: no early termination and the
  paper's shaped reward ``x_velocity - 3 (z - z_target)^2 - 0.1 |a|^2 + 1``.
* :class:`MBBLInvertedPendulumEnv`: InvertedPendulum with MBBL's reward ``-theta^2`` and no termination.
"""

from __future__ import annotations

from typing import Any

import numpy as np
from gymnasium import utils
from gymnasium.envs.mujoco.ant_v5 import AntEnv
from gymnasium.envs.mujoco.half_cheetah_v5 import HalfCheetahEnv
from gymnasium.envs.mujoco.hopper_v5 import HopperEnv
from gymnasium.envs.mujoco.inverted_pendulum_v5 import InvertedPendulumEnv
from gymnasium.envs.mujoco.swimmer_v5 import SwimmerEnv
from gymnasium.envs.mujoco.walker2d_v5 import Walker2dEnv
from gymnasium.spaces import Box
from numpy.typing import NDArray

from sb3_poplin.tasks.mbbl import MBBL_INVERTED_PENDULUM_ANGLE
from sb3_poplin.tasks.paper import (
    ANT_TARGET_HEIGHT,
    HOPPER_TARGET_HEIGHT,
    SHAPED_ALIVE_BONUS,
    SHAPED_CTRL_COST,
    SHAPED_HEIGHT_COST,
    WALKER_TARGET_HEIGHT,
)

# MujocoEnv.step's declared return type
StepResult = tuple[NDArray[np.float64], np.float64, bool, bool, dict[str, np.float64]]


class PETSCheetahEnv(HalfCheetahEnv):
    """
    HalfCheetah-v5 with the PETS observation: ``[(x' - x) / dt, qpos[1:], qvel]`` (18 entries).

    The first entry is the root's displacement over the last step divided by ``dt`` (0 right after a
    reset), so the forward reward ``obs'[0] - 0.1 |a|^2`` is a function of the next observation, and x
    itself is not observed. Never terminates.

    :param kwargs: passed to :class:`gymnasium.envs.mujoco.half_cheetah_v5.HalfCheetahEnv`
        (``exclude_current_positions_from_observation`` is fixed)
    """

    def __init__(self, **kwargs: Any) -> None:
        self._x_before: float | None = None
        super().__init__(exclude_current_positions_from_observation=False, **kwargs)
        utils.EzPickle.__init__(self, **kwargs)  # pickle / copy with this class's arguments, not the parent's

    def step(self, action: NDArray[np.float32]) -> StepResult:
        """
        :param action: the six joint torques
        :return: observation, reward, terminated, truncated, info (as HalfCheetah-v5)
        """
        self._x_before = float(self.data.qpos[0])
        return super().step(action)

    def reset_model(self) -> NDArray[np.float64]:
        """:return: the first observation, with forward velocity 0"""
        self._x_before = None
        return super().reset_model()

    def _get_obs(self) -> NDArray[np.float64]:
        """:return: the HalfCheetah observation with x kept, x replaced by the last step's mean x velocity"""
        observation = super()._get_obs()
        observation[0] = 0.0 if self._x_before is None else (self.data.qpos[0] - self._x_before) / self.dt
        return observation


SWIMMER_HEAD_OFFSET = 1.5  # the front end of the torso capsule, in the torso frame


class FixedSwimmerEnv(SwimmerEnv):
    """
    Swimmer-v5 paid the x velocity of its head: ``obs'[-1] - 1e-4 |a|^2``.

    Swimmer-v5 pays the velocity of the torso frame's origin (the middle of the middle link). Here the
    observation is Swimmer-v5's default one (x, y excluded) plus, as a last entry, the head's x
    displacement over the last step divided by ``dt`` (0 right after a reset). The head is the front end
    of the torso, at ``x_head = x + 1.5 cos(angle)`` with ``(x, angle) = (qpos[0], qpos[2])``. Never terminates.

    :param kwargs: passed to :class:`gymnasium.envs.mujoco.swimmer_v5.SwimmerEnv`
        (``exclude_current_positions_from_observation`` is fixed)
    """

    def __init__(self, **kwargs: Any) -> None:
        self._head_velocity = 0.0
        super().__init__(exclude_current_positions_from_observation=True, **kwargs)
        utils.EzPickle.__init__(self, **kwargs)
        size = self.observation_space.shape[0] + 1  # type: ignore[index]
        self.observation_space = Box(low=-np.inf, high=np.inf, shape=(size,), dtype=np.float64)

    def head_x(self) -> float:
        """:return: the x coordinate of the swimmer's head (front end of the torso), from ``qpos``"""
        return float(self.data.qpos[0] + SWIMMER_HEAD_OFFSET * np.cos(self.data.qpos[2]))

    def step(self, action: NDArray[np.float32]) -> StepResult:
        """
        :param action: the two joint torques
        :return: observation, reward, terminated (always False), truncated (False), info
        """
        head_before = self.head_x()
        self.do_simulation(action, self.frame_skip)
        self._head_velocity = (self.head_x() - head_before) / self.dt
        observation = self._get_obs()
        forward_reward = self._forward_reward_weight * self._head_velocity
        ctrl_cost = self.control_cost(action)
        info = {
            "x_position": np.float64(self.data.qpos[0]),
            "head_x_position": np.float64(self.head_x()),
            "head_x_velocity": np.float64(self._head_velocity),
            "reward_forward": np.float64(forward_reward),
            "reward_ctrl": np.float64(-ctrl_cost),
        }
        if self.render_mode == "human":
            self.render()
        return observation, np.float64(forward_reward - ctrl_cost), False, False, info

    def reset_model(self) -> NDArray[np.float64]:
        """:return: the first observation, with head velocity 0"""
        self._head_velocity = 0.0
        return super().reset_model()

    def _get_obs(self) -> NDArray[np.float64]:
        """:return: Swimmer-v5's observation followed by the head's x velocity"""
        return np.append(super()._get_obs(), self._head_velocity)


def _shaped_step(
    env: HopperEnv | Walker2dEnv | AntEnv, action: NDArray[np.float32], z_index: int, target_height: float
) -> StepResult:
    """
    One step of a no-termination locomotion task: ``(x' - x) / dt - 3 (z' - z_target)^2 - 0.1 |a|^2 + 1``.

    :param env: the MuJoCo env (its observation keeps the root position, ``qpos[0]`` first)
    :param action: the joint torques
    :param z_index: index of the root height in ``qpos``
    :param target_height: ``z_target``
    :return: observation, reward, terminated (always False), truncated (False), info
    """
    x_before = float(env.data.qpos[0])
    env.do_simulation(action, env.frame_skip)
    x_velocity = (float(env.data.qpos[0]) - x_before) / env.dt
    height = float(env.data.qpos[z_index])
    height_cost = SHAPED_HEIGHT_COST * (height - target_height) ** 2
    ctrl_cost = SHAPED_CTRL_COST * float(np.sum(np.square(action)))
    reward = x_velocity - height_cost - ctrl_cost + SHAPED_ALIVE_BONUS
    observation = env._get_obs()
    info = {
        "x_position": np.float64(env.data.qpos[0]),
        "x_velocity": np.float64(x_velocity),
        "z_position": np.float64(height),
        "reward_forward": np.float64(x_velocity),
        "reward_height": np.float64(-height_cost),
        "reward_ctrl": np.float64(-ctrl_cost),
        "reward_survive": np.float64(SHAPED_ALIVE_BONUS),
    }
    if env.render_mode == "human":
        env.render()
    return observation, np.float64(reward), False, False, info


class HopperNoTermEnv(HopperEnv):
    """
    Hopper-v5 without early termination, shaped reward ``x_vel - 3 (z - 1.3)^2 - 0.1 |a|^2 + 1``.

    Observation: Hopper-v5's with x kept, ``[qpos (6): x, z, angle, 3 joints; clip(qvel, -10, 10) (6)]``.

    :param kwargs: passed to :class:`gymnasium.envs.mujoco.hopper_v5.HopperEnv`
        (``terminate_when_unhealthy`` and ``exclude_current_positions_from_observation`` are fixed)
    """

    def __init__(self, **kwargs: Any) -> None:
        super().__init__(terminate_when_unhealthy=False, exclude_current_positions_from_observation=False, **kwargs)
        utils.EzPickle.__init__(self, **kwargs)

    def step(self, action: NDArray[np.float32]) -> StepResult:
        """
        :param action: the three joint torques
        :return: observation, reward, terminated (always False), truncated (False), info
        """
        return _shaped_step(self, action, z_index=1, target_height=HOPPER_TARGET_HEIGHT)


class Walker2dNoTermEnv(Walker2dEnv):
    """
    Walker2d-v5 without early termination, shaped reward ``x_vel - 3 (z - 1.3)^2 - 0.1 |a|^2 + 1``.

    Observation: Walker2d-v5's with x kept, ``[qpos (9): x, z, angle, 6 joints; clip(qvel, -10, 10) (9)]``.

    :param kwargs: passed to :class:`gymnasium.envs.mujoco.walker2d_v5.Walker2dEnv`
        (``terminate_when_unhealthy`` and ``exclude_current_positions_from_observation`` are fixed)
    """

    def __init__(self, **kwargs: Any) -> None:
        super().__init__(terminate_when_unhealthy=False, exclude_current_positions_from_observation=False, **kwargs)
        utils.EzPickle.__init__(self, **kwargs)

    def step(self, action: NDArray[np.float32]) -> StepResult:
        """
        :param action: the six joint torques
        :return: observation, reward, terminated (always False), truncated (False), info
        """
        return _shaped_step(self, action, z_index=1, target_height=WALKER_TARGET_HEIGHT)


class AntNoTermEnv(AntEnv):
    """
    Ant-v5 without early termination, shaped reward ``x_vel - 3 (z - 0.57)^2 - 0.1 |a|^2 + 1``.

    Observation: Ant-v5's with x, y kept and no contact forces, ``[qpos (15): x, y, z, quaternion (4),
    8 joints; qvel (14)]``. The x velocity is measured on ``qpos`` (Ant-v5 reads the torso's ``xpos``,
    which is one integration stage behind).

    :param kwargs: passed to :class:`gymnasium.envs.mujoco.ant_v5.AntEnv` (``terminate_when_unhealthy``,
        ``exclude_current_positions_from_observation`` and ``include_cfrc_ext_in_observation`` are fixed)
    """

    def __init__(self, **kwargs: Any) -> None:
        super().__init__(
            terminate_when_unhealthy=False,
            exclude_current_positions_from_observation=False,
            include_cfrc_ext_in_observation=False,
            **kwargs,
        )
        utils.EzPickle.__init__(self, **kwargs)

    def step(self, action: NDArray[np.float32]) -> StepResult:
        """
        :param action: the eight joint torques
        :return: observation, reward, terminated (always False), truncated (False), info
        """
        return _shaped_step(self, action, z_index=2, target_height=ANT_TARGET_HEIGHT)


class MBBLInvertedPendulumEnv(InvertedPendulumEnv):
    """
    MBBL's InvertedPendulum (``gym_invertedPendulum``): InvertedPendulum-v5's model and reset, reward ``-theta^2``
    on the observation *before* the step, no termination (registered as 101 steps: MBBL ends an episode once its
    step count exceeds 100).

    Observation: InvertedPendulum-v5's ``[cart x, pole angle, cart velocity, pole angular velocity]``. Action: the
    cart force in [-3, 3], the model's control range (MBBL passed actions to gym unscaled).

    :param kwargs: passed to :class:`gymnasium.envs.mujoco.inverted_pendulum_v5.InvertedPendulumEnv`
    """

    def __init__(self, **kwargs: Any) -> None:
        super().__init__(**kwargs)
        utils.EzPickle.__init__(self, **kwargs)

    def step(self, action: NDArray[np.float32]) -> StepResult:
        """
        :param action: the cart force
        :return: observation, reward (on the state before the step), terminated (always False), truncated, info
        """
        angle = float(self.data.qpos[MBBL_INVERTED_PENDULUM_ANGLE])
        self.do_simulation(action, self.frame_skip)
        observation = self._get_obs()
        if self.render_mode == "human":
            self.render()
        return observation, np.float64(-(angle**2)), False, False, {"angle": np.float64(angle)}
