"""Angle conventions shared by every model: radians, counter-clockwise positive, wrapped to (-pi, pi]."""

from __future__ import annotations

import math

TWO_PI = 2.0 * math.pi


def wrap_angle(angle: float) -> float:
    """Return ``angle`` wrapped to the half-open interval (-pi, pi].

    Guidance compares headings and line-of-sight angles that may each have wound up many turns;
    only their difference modulo a turn is meaningful.
    """
    wrapped = math.fmod(angle, TWO_PI)
    if wrapped > math.pi:
        wrapped -= TWO_PI
    elif wrapped <= -math.pi:
        wrapped += TWO_PI
    return wrapped
