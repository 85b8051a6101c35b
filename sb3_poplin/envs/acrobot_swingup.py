"""Continuous-action Acrobot swing-up: a two-link pendulum, actuated only at the elbow, must raise its tip."""

from __future__ import annotations

from typing import Any

import numpy as np
from numpy.typing import NDArray

from sb3_poplin.envs.integration import HandWrittenEnv, rk4

# Observation layout: [cos q1, sin q1, cos q2, sin q2, q1_dot, q2_dot] (gymnasium Acrobot's layout).
ACROBOT_COS1, ACROBOT_SIN1, ACROBOT_COS2, ACROBOT_SIN2, ACROBOT_Q1_DOT, ACROBOT_Q2_DOT = range(6)


class AcrobotSwingUpEnv(HandWrittenEnv):
    """
    Acrobot swing-up with a continuous elbow torque, after the POPLIN paper's Acrobot task.

    Angle convention (gymnasium's Acrobot): ``q1`` is the first link's angle from the downward vertical,
    ``q2`` the second link's angle relative to the first, both counterclockwise; ``q1 = q2 = 0`` hangs
    straight down, where every episode starts. With unit link lengths the tip is at height
    ``-cos(q1) - cos(q1 + q2)`` above the shoulder, from -2 (hanging) to 2 (upright), and the reward is
    that height on the state after the step: ``-(cos q1' + cos(q1' + q2'))``. The episode never
    terminates (registered with 200 steps, i.e. 20 s).

    The dynamics are the rigid two-link equations ``M(q) q_acc + c(q, q_dot) + g(q) = (0, tau)`` with
    link masses 1, lengths 1, centres of mass at 0.5 and moments of inertia 1 about the centre of mass
    (gymnasium's Acrobot constants), no friction and no velocity clipping, integrated with
    fourth-order Runge-Kutta, ``substeps`` steps per env step, the torque held constant. The action in
    [-1, 1] is scaled by ``max_torque``.

    :param max_torque: elbow torque (N m) at action 1
    :param dt: seconds per step
    :param substeps: Runge-Kutta steps per env step
    :param reset_noise_scale: the initial ``(q1, q2, q1_dot, q2_dot)`` is uniform in +-this
    :param render_mode: only ``None`` (no rendering)
    """

    gravity = 9.8
    link_mass = 1.0
    link_length = 1.0
    link_com = 0.5
    link_inertia = 1.0

    def __init__(
        self,
        max_torque: float = 2.0,
        dt: float = 0.1,
        substeps: int = 4,
        reset_noise_scale: float = 0.1,
        render_mode: str | None = None,
    ) -> None:
        super().__init__(np.full(6, np.inf), render_mode)
        self.max_torque = max_torque
        self.dt = dt
        self.substeps = substeps
        self.reset_noise_scale = reset_noise_scale
        self.state = np.zeros(4)

    def _derivatives(self, state: NDArray[np.float64], torque: float) -> NDArray[np.float64]:
        """
        Solve the 2x2 equations of motion for the joint accelerations.

        :param state: ``(q1, q2, q1_dot, q2_dot)``
        :param torque: elbow torque (N m)
        :return: the time derivative of ``state``
        """
        q1, q2, q1_dot, q2_dot = state
        m, l1, lc, inertia, g = self.link_mass, self.link_length, self.link_com, self.link_inertia, self.gravity
        cos2 = np.cos(q2)
        coupling = m * l1 * lc  # the product that scales every term linking the two links
        m22 = m * lc**2 + inertia
        m12 = m22 + coupling * cos2
        m11 = m * lc**2 + inertia + m * l1**2 + m22 + 2.0 * coupling * cos2
        centrifugal = coupling * np.sin(q2)
        c1 = -centrifugal * (2.0 * q1_dot * q2_dot + q2_dot**2)
        c2 = centrifugal * q1_dot**2
        gravity2 = m * g * lc * np.sin(q1 + q2)
        gravity1 = (m * lc + m * l1) * g * np.sin(q1) + gravity2
        rhs1 = -c1 - gravity1
        rhs2 = torque - c2 - gravity2
        determinant = m11 * m22 - m12**2
        q1_acc = (m22 * rhs1 - m12 * rhs2) / determinant
        q2_acc = (m11 * rhs2 - m12 * rhs1) / determinant
        return np.array([q1_dot, q2_dot, q1_acc, q2_acc])

    def _observation(self) -> NDArray[np.float64]:
        """:return: ``[cos q1, sin q1, cos q2, sin q2, q1_dot, q2_dot]``"""
        q1, q2, q1_dot, q2_dot = self.state
        return np.array([np.cos(q1), np.sin(q1), np.cos(q2), np.sin(q2), q1_dot, q2_dot], dtype=np.float64)

    def _initial_state(self) -> NDArray[np.float64]:
        """The state at a reset."""
        return self.np_random.uniform(-self.reset_noise_scale, self.reset_noise_scale, size=4)

    def step(self, action: NDArray[np.float32]) -> tuple[NDArray[np.float64], float, bool, bool, dict[str, Any]]:
        """
        :param action: elbow torque in [-1, 1] (clipped), scaled by ``max_torque``
        :return: observation, reward, terminated (always False), truncated (False: the TimeLimit truncates), info
        """
        torque = self.max_torque * float(np.clip(np.asarray(action, dtype=np.float64).reshape(-1)[0], -1.0, 1.0))
        self.state = rk4(self._derivatives, self.state, torque, self.dt, self.substeps)
        observation = self._observation()
        cos1, sin1 = observation[ACROBOT_COS1], observation[ACROBOT_SIN1]
        cos2, sin2 = observation[ACROBOT_COS2], observation[ACROBOT_SIN2]
        tip_height = -(cos1 + (cos1 * cos2 - sin1 * sin2))
        return observation, float(tip_height), False, False, {"torque": torque}
