"""
The MBBL benchmark's classic-control tasks that the POPLIN paper uses (Wang et al. 2019, "Benchmarking model-based
reinforcement learning"): Pendulum, Acrobot and Cartpole, as MBBL wraps gym's ``Pendulum-v0``, ``Acrobot-v1`` and
``CartPole-v1``.

What MBBL changes from gym, and these envs reproduce:

* the reward is a function of the observation *before* the step (and of the action);
* gym's termination is ignored and every episode has a fixed length (registered as 201 steps: MBBL ends an episode
  once its step count exceeds 200);
* the action is a 1-D continuous value in [-1, 1]: Pendulum scales it by the maximum torque 2, Acrobot maps it to
  gym's three torques (-1 below -0.33, 0 up to 0.33, +1 above), Cartpole pushes right when it is positive and left
  otherwise (bang-bang, force 10 N).

The dynamics are gym's, written here in numpy (Pendulum-v0's explicit update, Acrobot-v1's one RK4 step of 0.2 s
with its velocity bounds, CartPole-v1's Euler step of 0.02 s), reusing the physics of the package's swing-up envs.
"""

from __future__ import annotations

from typing import Any

import gymnasium as gym
import numpy as np
from numpy.typing import NDArray

from sb3_poplin.envs.acrobot_swingup import ACROBOT_COS1, ACROBOT_COS2, ACROBOT_SIN1, ACROBOT_SIN2, AcrobotSwingUpEnv
from sb3_poplin.envs.cartpole_swingup import CartPoleSwingUpEnv
from sb3_poplin.envs.integration import HandWrittenEnv, rk4

# ---------------------------------------------------------------------------------------------------------- Pendulum
# obs = [cos(theta), sin(theta), theta_dot], theta = 0 upright (gym's convention)
PENDULUM_COS, PENDULUM_SIN, PENDULUM_THETA_DOT = 0, 1, 2
PENDULUM_MAX_TORQUE = 2.0
PENDULUM_SIN_COST = 0.1
PENDULUM_VELOCITY_COST = 0.1
PENDULUM_TORQUE_COST = 0.001


def _first(action: NDArray[np.float32]) -> float:
    """:return: the first (only) entry of an action, as a float"""
    return float(np.asarray(action, dtype=np.float64).reshape(-1)[0])


class MBBLPendulumEnv(HandWrittenEnv):
    """
    MBBL's Pendulum (``gym_pendulum``): gym's ``Pendulum-v0`` with MBBL's reward and action scaling.

    State ``(theta, theta_dot)`` with ``theta = 0`` upright (gym's convention). One step of ``dt = 0.05`` s with the
    torque ``u = 2 clip(a, -1, 1)``: ``theta_dot' = theta_dot + (3 g / (2 l) sin(theta) + 3 u / (m l^2)) dt``,
    ``theta' = theta + theta_dot' dt``, then ``theta_dot'`` clipped to +-8 (Pendulum-v0 clips after the position
    update), ``g = 10``, ``m = l = 1``. Observation ``[cos(theta), sin(theta), theta_dot]``.

    Reward on the observation before the step: ``-(cos(theta) + 0.1 |sin(theta)| + 0.1 theta_dot^2 + 0.001 u^2)``,
    MBBL's formula read literally with gym's angle convention: it is largest (about +1 per step) with the pendulum
    hanging *down* and at rest. Reset: ``theta`` uniform in [-pi, pi], ``theta_dot`` in [-1, 1]. Never terminates.

    :param render_mode: only ``None`` (no rendering)
    """

    gravity = 10.0
    mass = 1.0
    length = 1.0
    dt = 0.05
    max_speed = 8.0

    def __init__(self, render_mode: str | None = None) -> None:
        super().__init__(np.array([1.0, 1.0, np.inf]), render_mode)
        self.state = np.zeros(2)

    def _observation(self) -> NDArray[np.float64]:
        """:return: ``[cos(theta), sin(theta), theta_dot]``"""
        theta, theta_dot = self.state
        return np.array([np.cos(theta), np.sin(theta), theta_dot], dtype=np.float64)

    def _initial_state(self) -> NDArray[np.float64]:
        """The state at a reset."""
        return self.np_random.uniform(low=[-np.pi, -1.0], high=[np.pi, 1.0])

    def step(self, action: NDArray[np.float32]) -> tuple[NDArray[np.float64], float, bool, bool, dict[str, Any]]:
        """
        :param action: in [-1, 1] (clipped), scaled by the maximum torque 2
        :return: observation, reward (on the state before the step), terminated (always False), truncated, info
        """
        torque = PENDULUM_MAX_TORQUE * float(np.clip(_first(action), -1.0, 1.0))
        cos, sin, theta_dot = self._observation()
        reward = -(cos + PENDULUM_SIN_COST * abs(sin) + PENDULUM_VELOCITY_COST * theta_dot**2)
        reward -= PENDULUM_TORQUE_COST * torque**2
        theta = self.state[0]
        acceleration = 3.0 * self.gravity / (2.0 * self.length) * np.sin(theta)
        acceleration += 3.0 / (self.mass * self.length**2) * torque
        new_theta_dot = theta_dot + acceleration * self.dt
        new_theta = theta + new_theta_dot * self.dt
        self.state = np.array([new_theta, np.clip(new_theta_dot, -self.max_speed, self.max_speed)])
        return self._observation(), float(reward), False, False, {"torque": torque}


# ----------------------------------------------------------------------------------------------------------- Acrobot
# obs = [cos q1, sin q1, cos q2, sin q2, q1_dot, q2_dot] (AcrobotSwingUpEnv's layout); q1 = q2 = 0 hangs down
ACROBOT_ACTION_THRESHOLDS = (-0.33, 0.33)
ACROBOT_MAX_VELOCITIES = (4.0 * np.pi, 9.0 * np.pi)


class MBBLAcrobotEnv(AcrobotSwingUpEnv):
    """
    MBBL's Acrobot (``gym_acrobot``): gym's ``Acrobot-v1`` with a continuous action and the tip height as reward.

    The action ``a`` in [-1, 1] picks the elbow torque: -1 if ``a < -0.33``, 0 if ``a < 0.33``, else +1. The
    dynamics are gym's (the rigid two-link equations with unit masses, lengths and moments of inertia, centres of
    mass at 0.5; one fourth-order Runge-Kutta step of 0.2 s), then the angles are wrapped to [-pi, pi) and the
    velocities clipped to +-4 pi (shoulder) and +-9 pi (elbow). Observation ``[cos q1, sin q1, cos q2, sin q2,
    q1_dot, q2_dot]`` with ``q1 = q2 = 0`` hanging down. Reward on the observation before the step: the tip height
    ``-(cos q1 + cos(q1 + q2))``, from -2 (hanging) to 2 (upright). Reset: the four state variables uniform in
    +-0.1. Never terminates (gym's goal test is ignored).

    :param render_mode: only ``None`` (no rendering)
    """

    def __init__(self, render_mode: str | None = None) -> None:
        super().__init__(max_torque=1.0, dt=0.2, substeps=1, reset_noise_scale=0.1, render_mode=render_mode)

    @staticmethod
    def torque(action: float) -> float:
        """
        :param action: the continuous action
        :return: gym's torque for it: -1, 0 or 1
        """
        low, high = ACROBOT_ACTION_THRESHOLDS
        return -1.0 if action < low else (0.0 if action < high else 1.0)

    def step(self, action: NDArray[np.float32]) -> tuple[NDArray[np.float64], float, bool, bool, dict[str, Any]]:
        """
        :param action: in [-1, 1], mapped to one of the three torques
        :return: observation, reward (the tip height before the step), terminated (always False), truncated, info
        """
        torque = self.torque(_first(action))
        before = self._observation()
        cos1, sin1, cos2, sin2 = before[ACROBOT_COS1], before[ACROBOT_SIN1], before[ACROBOT_COS2], before[ACROBOT_SIN2]
        reward = -(cos1 + (cos1 * cos2 - sin1 * sin2))
        state = rk4(self._derivatives, self.state, torque, self.dt, self.substeps)
        state[:2] = (state[:2] + np.pi) % (2.0 * np.pi) - np.pi
        state[2:] = np.clip(state[2:], -np.asarray(ACROBOT_MAX_VELOCITIES), ACROBOT_MAX_VELOCITIES)
        self.state = state
        return self._observation(), float(reward), False, False, {"torque": torque}


# ---------------------------------------------------------------------------------------------------------- Cartpole
# obs = [x, x_dot, theta, theta_dot], theta = 0 upright (gym's CartPole state, unwrapped)
CARTPOLE_X, CARTPOLE_X_DOT, CARTPOLE_THETA, CARTPOLE_THETA_DOT = 0, 1, 2, 3
CARTPOLE_X_COST = 0.01


class MBBLCartpoleEnv(CartPoleSwingUpEnv):
    """
    MBBL's Cartpole (``gym_cartpole``): gym's ``CartPole-v1`` balance task, bang-bang force, no termination.

    The pole starts near upright: ``(x, x_dot, theta, theta_dot)`` uniform in +-0.05 (gym's reset). The action
    ``a`` in [-1, 1] pushes the cart with +10 N if ``a > 0``, else -10 N. The dynamics are gym's cart-pole
    equations (those of :class:`~sb3_poplin.envs.cartpole_swingup.CartPoleSwingUpEnv`) with one explicit Euler step
    of 0.02 s (gym's ``euler``: positions move with the old velocities). Observation: the raw state
    ``[x, x_dot, theta, theta_dot]`` (theta not wrapped). Reward on the observation before the step:
    ``cos(theta) - 0.01 x^2``. Never terminates (gym's pole-angle and cart-position limits are ignored).

    :param render_mode: only ``None`` (no rendering)
    """

    def __init__(self, render_mode: str | None = None) -> None:
        super().__init__(max_force=10.0, dt=0.02, reset_noise_scale=0.05, render_mode=render_mode)
        self.observation_space = gym.spaces.Box(-np.inf, np.inf, shape=(4,), dtype=np.float64)

    def _observation(self) -> NDArray[np.float64]:
        """:return: ``[x, x_dot, theta, theta_dot]``"""
        return self.state.astype(np.float64, copy=True)

    def _initial_state(self) -> NDArray[np.float64]:
        """The state at a reset (near upright)."""
        return self.np_random.uniform(-self.reset_noise_scale, self.reset_noise_scale, size=4)

    def step(self, action: NDArray[np.float32]) -> tuple[NDArray[np.float64], float, bool, bool, dict[str, Any]]:
        """
        :param action: positive pushes right, anything else left
        :return: observation, reward (on the state before the step), terminated (always False), truncated, info
        """
        force = self.max_force if _first(action) > 0.0 else -self.max_force
        x, _, theta, _ = self.state
        reward = float(np.cos(theta) - CARTPOLE_X_COST * x**2)
        self.state = self.state + self.dt * self._derivatives(self.state, force)
        return self._observation(), reward, False, False, {"force": force}
