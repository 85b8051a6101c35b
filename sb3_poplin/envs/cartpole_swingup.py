"""Continuous-action cart-pole swing-up: the pole starts hanging down and must be swung up and balanced."""

from __future__ import annotations

from typing import Any

import numpy as np
from numpy.typing import NDArray

from sb3_poplin.envs.integration import HandWrittenEnv, rk4

# Observation layout: [cart x, cart velocity, cos(theta), sin(theta), pole angular velocity], theta = 0 upright.
CARTPOLE_X, CARTPOLE_X_DOT, CARTPOLE_COS, CARTPOLE_SIN, CARTPOLE_THETA_DOT = 0, 1, 2, 3, 4
# Reward on the state after the step: cos(theta') - CARTPOLE_X_COST * x'^2
CARTPOLE_X_COST = 0.01


class CartPoleSwingUpEnv(HandWrittenEnv):
    """
    Cart-pole swing-up with a continuous force, after the POPLIN paper's Cartpole task.

    The state is ``(x, x_dot, theta, theta_dot)`` with ``theta`` the pole angle from upright (positive
    clockwise, i.e. towards +x), so an episode starts near ``theta = pi`` (hanging down). The dynamics are
    the classic frictionless cart-pole equations (Barto, Sutton and Anderson, 1983; the constants of
    gymnasium's ``CartPole``): with ``F`` the force, ``M = m_cart + m_pole`` and ``l`` the pole half-length,

    ``theta_acc = (g sin(theta) - cos(theta) q) / (l (4/3 - m_pole cos(theta)^2 / M))``,
    ``q = (F + m_pole l theta_dot^2 sin(theta)) / M``,
    ``x_acc = q - m_pole l theta_acc cos(theta) / M``,

    integrated with one fourth-order Runge-Kutta step of ``dt`` per env step, the force held constant.
    The action in [-1, 1] is scaled by ``max_force``. The reward is ``cos(theta') - 0.01 x'^2`` on the
    state after the step (so it is a function of the next observation only); the episode never
    terminates (registered with 200 steps, i.e. 10 s).

    :param max_force: force (N) at action 1
    :param dt: seconds per step
    :param reset_noise_scale: the initial state is ``(0, 0, pi, 0)`` plus uniform noise in +-this
    :param render_mode: only ``None`` (no rendering)
    """

    gravity = 9.8
    cart_mass = 1.0
    pole_mass = 0.1
    pole_half_length = 0.5

    def __init__(
        self,
        max_force: float = 10.0,
        dt: float = 0.05,
        reset_noise_scale: float = 0.05,
        render_mode: str | None = None,
    ) -> None:
        super().__init__(np.full(5, np.inf), render_mode)
        self.max_force = max_force
        self.dt = dt
        self.reset_noise_scale = reset_noise_scale
        self.state = np.zeros(4)

    def _derivatives(self, state: NDArray[np.float64], force: float) -> NDArray[np.float64]:
        """
        :param state: ``(x, x_dot, theta, theta_dot)``
        :param force: horizontal force on the cart (N)
        :return: the time derivative of ``state``
        """
        _, x_dot, theta, theta_dot = state
        total_mass = self.cart_mass + self.pole_mass
        sin, cos = np.sin(theta), np.cos(theta)
        pole_moment = self.pole_mass * self.pole_half_length
        q = (force + pole_moment * theta_dot**2 * sin) / total_mass
        theta_acc = (self.gravity * sin - cos * q) / (
            self.pole_half_length * (4.0 / 3.0 - self.pole_mass * cos**2 / total_mass)
        )
        x_acc = q - pole_moment * theta_acc * cos / total_mass
        return np.array([x_dot, x_acc, theta_dot, theta_acc])

    def _observation(self) -> NDArray[np.float64]:
        """:return: ``[x, x_dot, cos(theta), sin(theta), theta_dot]``"""
        x, x_dot, theta, theta_dot = self.state
        return np.array([x, x_dot, np.cos(theta), np.sin(theta), theta_dot], dtype=np.float64)

    def _initial_state(self) -> NDArray[np.float64]:
        """The state at a reset."""
        noise = self.np_random.uniform(-self.reset_noise_scale, self.reset_noise_scale, size=4)
        return np.array([0.0, 0.0, np.pi, 0.0]) + noise

    def step(self, action: NDArray[np.float32]) -> tuple[NDArray[np.float64], float, bool, bool, dict[str, Any]]:
        """
        :param action: force in [-1, 1] (clipped), scaled by ``max_force``
        :return: observation, reward, terminated (always False), truncated (False: the TimeLimit truncates), info
        """
        force = self.max_force * float(np.clip(np.asarray(action, dtype=np.float64).reshape(-1)[0], -1.0, 1.0))
        self.state = rk4(self._derivatives, self.state, force, self.dt)
        observation = self._observation()
        reward = float(observation[CARTPOLE_COS] - CARTPOLE_X_COST * observation[CARTPOLE_X] ** 2)
        return observation, reward, False, False, {"force": force}
