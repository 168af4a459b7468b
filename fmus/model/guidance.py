"""Trajectory shaping guidance (Erekson, Sharma, Ratnoo, Gerdes), the paper's equations 2, 3 and 5.

A vehicle at (x, y) with heading gamma_v chases a target at (x_t, y_t) with heading gamma_t. With the
line-of-sight angle lambda and distance d between them, the lateral acceleration command is

* regular (eq. 2): a = V^2/d * (4 (lambda - gamma_v) + 2 (lambda - gamma_t))
* sine    (eq. 5): a = V^2/d * (4 sin(lambda - gamma_v) + 2 sin(lambda - gamma_t))

The sine law has the desired circle as an exact equilibrium; the regular law settles at an offset.

The longitudinal side is one equation used twice: the speed that restores the spacing d* is
``spacing_speed(V, d, d*) = V d*/d``. The virtual target moves at ``spacing_speed(V_1, d_1, d*)``
(eq. 3) and, in a platoon, vehicle i is commanded ``spacing_speed(V_{i+1}, d_{i+1}, d*)``, the
speed and gap of the vehicle *behind* it (velocity information flows forward). The paper's text
prints d_i in that command, but its linearization (the A_tv block) needs d_{i+1}, and with d_i a
platoon of four is unstable; see docs/model.md, `platoon analyze` and tests/test_analysis.py.
"""

from __future__ import annotations

import math

from .angles import wrap_angle

LAWS = ("regular", "sine")


def line_of_sight(x: float, y: float, target_x: float, target_y: float) -> tuple[float, float]:
    """Distance d and line-of-sight angle lambda from the vehicle to its target."""
    dx = target_x - x
    dy = target_y - y
    return math.hypot(dx, dy), math.atan2(dy, dx)


def lateral_acceleration(
    law: str, speed: float, distance: float, los: float, heading: float, target_heading: float
) -> float:
    """Lateral acceleration command of the regular (eq. 2) or sine (eq. 5) law, in m/s^2.

    Angle differences are wrapped to (-pi, pi] so that wound-up headings do not matter.
    """
    vehicle_error = wrap_angle(los - heading)
    target_error = wrap_angle(los - target_heading)
    gain = speed * speed / distance
    if law == "sine":
        return gain * (4.0 * math.sin(vehicle_error) + 2.0 * math.sin(target_error))
    if law == "regular":
        return gain * (4.0 * vehicle_error + 2.0 * target_error)
    raise ValueError(f"unknown guidance law {law!r}; expected one of {', '.join(LAWS)}")


def spacing_speed(speed: float, gap: float, d_star: float) -> float:
    """Speed V d*/d that restores the spacing d*: eq. 3 for the virtual target, V_cmd in a platoon."""
    return speed * d_star / gap


def spacing_speed_rate(
    speed: float, speed_rate: float, gap: float, gap_rate: float, d_star: float
) -> float:
    """Time derivative of :func:`spacing_speed`, for receivers that extrapolate it inside a step."""
    return d_star * (speed_rate * gap - speed * gap_rate) / (gap * gap)


def speed_loop(k_v: float, commanded_speed: float, speed: float) -> float:
    """First-order speed loop dV/dt = k_v (V_cmd - V)."""
    return k_v * (commanded_speed - speed)


def equilibrium_angles(d_star: float, radius: float) -> tuple[float, float]:
    """The paper's equilibrium (eq. 4) relative headings (alpha_t, alpha_v) on a circle of radius R."""
    alpha = math.asin(d_star / (2.0 * radius))
    return alpha, -alpha
