"""How a component sees a neighbour between two communication points.

A co-simulation master exchanges values only at communication points. With ``hold`` a component
keeps each input constant over the step (zero-order hold, what every common master does). With
``extrapolate`` it moves its inputs to the time it needs: the target is dead-reckoned along an arc
(its speed and speed rate along the path, its turn rate bending the path: never a straight-line
move with a frozen heading, which is far worse than holding), and the speed-chain inputs (speed, gap)
follow straight lines with the rates the sender outputs. Every sample carries the time it describes,
so extrapolation also runs backwards (Gauss-Seidel hands over values from the end of the step); an
arc run backwards is still the same arc. See docs/coupling.md for the measured effect.
"""

from __future__ import annotations

import math

COUPLING_MODES = ("hold", "extrapolate")

_SERIES_LIMIT = 1e-3


def _arc_factors(turn: float) -> tuple[float, float]:
    """(sin u / u, (1 - cos u) / u), with their Taylor series near u = 0 to avoid cancellation."""
    if abs(turn) < _SERIES_LIMIT:
        u2 = turn * turn
        return 1.0 - u2 / 6.0 + u2 * u2 / 120.0, turn * (0.5 - u2 / 24.0 + u2 * u2 / 720.0)
    return math.sin(turn) / turn, (1.0 - math.cos(turn)) / turn


def arc_extrapolate(
    x: float,
    y: float,
    heading: float,
    speed: float,
    speed_rate: float,
    turn_rate: float,
    dt: float,
) -> tuple[float, float, float, float]:
    """Pose and speed of a mover dt seconds after (or before, dt < 0) it was sampled.

    The mover keeps the curvature turn_rate/speed it had at the sample and travels the arc length
    speed*dt + speed_rate*dt^2/2. Both the position and the heading follow the same arc, so a point
    on a circle, tangent to it, stays on it exactly.
    """
    arc_length = dt * (speed + 0.5 * speed_rate * dt)
    curvature = turn_rate / speed if speed != 0.0 else 0.0
    turn = curvature * arc_length
    along, across = _arc_factors(turn)
    c = math.cos(heading)
    s = math.sin(heading)
    return (
        x + arc_length * (along * c - across * s),
        y + arc_length * (along * s + across * c),
        heading + turn,
        speed + speed_rate * dt,
    )


def linear_extrapolate(value: float, rate: float, dt: float) -> float:
    """value + rate * dt: the speed-chain inputs between communication points."""
    return value + rate * dt


def check_coupling(mode: str) -> None:
    if mode not in COUPLING_MODES:
        raise ValueError(f"unknown coupling {mode!r}; expected one of {', '.join(COUPLING_MODES)}")
