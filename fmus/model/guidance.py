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

Beyond the paper, two speed laws of the platooning literature (``SPEED_LAWS``; docs/model.md, section 11)
take the gap d_i to the vehicle *ahead* from an on-board sensor instead:

* acc, a constant time gap (desired gap r + h V): ``time_gap_speed(d, r, h) = (d - r)/h``;
* cacc, after Ploeg et al. (ITSC 2011): the spacing error ``spacing_error(d, r, h, V) = d - r - h V``,
  the desired acceleration ``cacc_acceleration(V_prev, V, e, h, k_p) = (V_prev - V + k_p e)/h``, realised
  through the first-order speed loop as ``speed_for_acceleration(V, a, k_v) = V + a/k_v``.
"""

from __future__ import annotations

import math

from .angles import wrap_angle

LAWS = ("regular", "sine")
# The speed laws: the paper's V d*/d chain, a constant-time-gap ACC, Ploeg's CACC (adapted).
SPEED_LAWS = ("paper", "acc", "cacc")
# The laws that measure the gap to the vehicle ahead with the on-board sensor (the sensor.* inputs).
SENSING_LAWS = ("acc", "cacc")


def line_of_sight(x: float, y: float, target_x: float, target_y: float) -> tuple[float, float]:
    """Distance d and line-of-sight angle lambda from the vehicle to its target."""
    dx = target_x - x
    dy = target_y - y
    return math.hypot(dx, dy), math.atan2(dy, dx)


def distance(x: float, y: float, target_x: float, target_y: float) -> float:
    """The distance of :func:`line_of_sight` alone (the sensed gap needs no angle)."""
    return math.hypot(target_x - x, target_y - y)


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


def time_gap_speed(gap: float, standstill_gap: float, time_gap: float) -> float:
    """Constant-time-gap policy (ACC): the speed whose desired gap r + h V is the gap d, (d - r)/h."""
    return (gap - standstill_gap) / time_gap


def spacing_error(gap: float, standstill_gap: float, time_gap: float, speed: float) -> float:
    """Spacing error of the constant-time-gap policy, e = d - (r + h V)."""
    return gap - standstill_gap - time_gap * speed


def cacc_acceleration(
    predecessor_speed: float, speed: float, error: float, time_gap: float, gain: float
) -> float:
    """Desired acceleration of the CACC law, a = (V_prev - V + k_p e)/h: it makes de/dt = -k_p e."""
    return (predecessor_speed - speed + gain * error) / time_gap


def speed_for_acceleration(speed: float, acceleration: float, k_v: float) -> float:
    """The speed command under which the speed loop dV/dt = k_v (V_cmd - V) accelerates at a."""
    return speed + acceleration / k_v


def speed_loop(k_v: float, commanded_speed: float, speed: float) -> float:
    """First-order speed loop dV/dt = k_v (V_cmd - V)."""
    return k_v * (commanded_speed - speed)


def equilibrium_angles(d_star: float, radius: float) -> tuple[float, float]:
    """The paper's equilibrium (eq. 4) relative headings (alpha_t, alpha_v) on a circle of radius R."""
    alpha = math.asin(d_star / (2.0 * radius))
    return alpha, -alpha
