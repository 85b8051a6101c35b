"""Numerical integration shared by the package's hand-written (numpy) envs."""

from __future__ import annotations

from collections.abc import Callable

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
