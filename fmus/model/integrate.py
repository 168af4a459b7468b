"""Fixed-step Runge-Kutta 4 on plain lists, the integrator of every continuous state in the project."""

from __future__ import annotations

import math
from typing import Callable

Derivative = Callable[[float, list[float]], list[float]]


def rk4_step(f: Derivative, t: float, y: list[float], h: float) -> list[float]:
    """One classical RK4 step of size h from (t, y)."""
    half = 0.5 * h
    k1 = f(t, y)
    k2 = f(t + half, [yi + half * ki for yi, ki in zip(y, k1)])
    k3 = f(t + half, [yi + half * ki for yi, ki in zip(y, k2)])
    k4 = f(t + h, [yi + h * ki for yi, ki in zip(y, k3)])
    sixth = h / 6.0
    return [
        yi + sixth * (a + 2.0 * b + 2.0 * c + d) for yi, a, b, c, d in zip(y, k1, k2, k3, k4)
    ]


def substep_count(step: float, max_substep: float) -> int:
    """Number of equal substeps no longer than ``max_substep`` that make up ``step``.

    The small tolerance keeps 0.01 / 0.01 at one substep despite floating-point division.
    """
    return max(1, math.ceil(step / max_substep - 1e-9))


def integrate(f: Derivative, t: float, y: list[float], step: float, max_substep: float) -> list[float]:
    """Advance y from t to t + step with equal RK4 substeps no longer than ``max_substep``."""
    n = substep_count(step, max_substep)
    h = step / n
    for k in range(n):
        y = rk4_step(f, t + k * h, y, h)
    return y
