"""What the package's hand-written (numpy) envs share: their base class and numerical integration."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import gymnasium as gym
import numpy as np
from numpy.typing import NDArray

Derivatives = Callable[[NDArray[np.float64], float], NDArray[np.float64]]


def rk4(
    derivatives: Derivatives, state: NDArray[np.float64], control: float, dt: float, substeps: int = 1
) -> NDArray[np.float64]:
    """
    Integrate ``d state / dt = derivatives(state, control)`` over ``dt`` with ``substeps`` classic
    fourth-order Runge-Kutta steps, the control held constant.

    :param derivatives: the time derivative of the state
    :param state: the state at the start
    :param control: the control input, constant over the interval
    :param dt: the interval length
    :param substeps: Runge-Kutta steps over the interval
    :return: the state after ``dt``
    """
    h = dt / substeps
    for _ in range(substeps):
        k1 = derivatives(state, control)
        k2 = derivatives(state + 0.5 * h * k1, control)
        k3 = derivatives(state + 0.5 * h * k2, control)
        k4 = derivatives(state + h * k3, control)
        state = state + h / 6.0 * (k1 + 2.0 * k2 + 2.0 * k3 + k4)
    return state


class HandWrittenEnv(gym.Env[NDArray[np.float64], NDArray[np.float32]]):
    """
    Base of the package's numpy envs: one action in [-1, 1], a flat float64 observation, no rendering.

    :param observation_high: the observation bounds (symmetric)
    :param render_mode: only ``None``
    """

    metadata: dict[str, Any] = {"render_modes": []}  # noqa: RUF012

    def __init__(self, observation_high: NDArray[np.float64], render_mode: str | None = None) -> None:
        if render_mode is not None:
            raise ValueError(f"{type(self).__name__} has no rendering; got render_mode={render_mode!r}")
        self.render_mode = render_mode
        self.action_space = gym.spaces.Box(-1.0, 1.0, shape=(1,), dtype=np.float32)
        self.observation_space = gym.spaces.Box(-observation_high, observation_high, dtype=np.float64)
        self.state = np.zeros(0)

    def _initial_state(self) -> NDArray[np.float64]:
        """The state at a reset, drawn from ``self.np_random``."""
        raise NotImplementedError

    def _observation(self) -> NDArray[np.float64]:
        """The observation of ``self.state``."""
        raise NotImplementedError

    def reset(
        self, *, seed: int | None = None, options: dict[str, Any] | None = None
    ) -> tuple[NDArray[np.float64], dict[str, Any]]:
        """
        :param seed: seeds the env's random generator
        :param options: unused
        :return: the first observation and an empty info dict
        """
        gym.Env.reset(self, seed=seed)
        self.state = self._initial_state()
        return self._observation(), {}
