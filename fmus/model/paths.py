"""Paths a virtual target can move along, parametrized by arc length s.

Only the lead vehicle's virtual target knows the path. Each path answers three questions: where is
the point at arc length s and which way does it face (``pose_at``), how curved is the path there
(``curvature``, signed, positive turning left), and how far is a point from it (``signed_distance``,
the path error of a pose). New shapes implement the same protocol and register in ``PATH_KINDS``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Protocol


class Path(Protocol):
    def pose_at(self, s: float) -> tuple[float, float, float]:
        """Position (x, y) and tangent heading at arc length s."""

    def curvature(self, s: float) -> float:
        """Signed curvature at arc length s, 1/m (positive: turning left)."""

    def signed_distance(self, x: float, y: float) -> float:
        """Signed distance of (x, y) from the path, m (circle: r - R, outside positive)."""

    def arc_for_chord(self, chord: float) -> float:
        """Arc length between two points of the path that are ``chord`` apart in a straight line."""

    def outward_normal(self, x: float, y: float) -> tuple[float, float]:
        """Unit vector from the path towards positive signed distance, at (x, y)."""


@dataclass(frozen=True)
class CirclePath:
    """Circle of ``radius`` about (center_x, center_y); s = 0 at angle ``start_angle`` from the centre.

    ``direction`` is +1 for counter-clockwise travel, -1 for clockwise.
    """

    radius: float
    center_x: float = 0.0
    center_y: float = 0.0
    direction: int = 1
    start_angle: float = 0.0

    def pose_at(self, s: float) -> tuple[float, float, float]:
        angle = self.start_angle + self.direction * s / self.radius
        x = self.center_x + self.radius * math.cos(angle)
        y = self.center_y + self.radius * math.sin(angle)
        return x, y, angle + self.direction * 0.5 * math.pi

    def curvature(self, s: float) -> float:
        return self.direction / self.radius

    def signed_distance(self, x: float, y: float) -> float:
        return math.hypot(x - self.center_x, y - self.center_y) - self.radius

    def outward_normal(self, x: float, y: float) -> tuple[float, float]:
        r = math.hypot(x - self.center_x, y - self.center_y)
        return (x - self.center_x) / r, (y - self.center_y) / r

    def arc_for_chord(self, chord: float) -> float:
        if chord > 2.0 * self.radius:
            raise ValueError(f"a chord of {chord} m does not fit a circle of radius {self.radius} m")
        return 2.0 * self.radius * math.asin(chord / (2.0 * self.radius))


@dataclass(frozen=True)
class LinePath:
    """Straight line through (origin_x, origin_y) heading ``heading``; s = 0 at the origin."""

    origin_x: float = 0.0
    origin_y: float = 0.0
    heading: float = 0.0

    def pose_at(self, s: float) -> tuple[float, float, float]:
        return (
            self.origin_x + s * math.cos(self.heading),
            self.origin_y + s * math.sin(self.heading),
            self.heading,
        )

    def curvature(self, s: float) -> float:
        return 0.0

    def signed_distance(self, x: float, y: float) -> float:
        """Distance to the right of the direction of travel is positive, like outside a CCW circle."""
        dx = x - self.origin_x
        dy = y - self.origin_y
        return dx * math.sin(self.heading) - dy * math.cos(self.heading)

    def outward_normal(self, x: float, y: float) -> tuple[float, float]:
        return math.sin(self.heading), -math.cos(self.heading)

    def arc_for_chord(self, chord: float) -> float:
        return chord


PATH_KINDS = ("circle", "line")


def make_path(
    kind: str,
    radius: float = 50.0,
    x0: float = 0.0,
    y0: float = 0.0,
    heading: float = 0.0,
    direction: int = 1,
) -> CirclePath | LinePath:
    """Build a path from the flat parameters the VirtualTarget FMU and the config share.

    (x0, y0) is the circle's centre or the line's origin; ``heading`` is the line's direction or the
    angle of the circle's s = 0 point seen from its centre.
    """
    if kind == "circle":
        if not (math.isfinite(radius) and radius > 0.0):
            raise ValueError(f"path radius must be > 0 m, got {radius}")
        if direction not in (1, -1):
            raise ValueError(f"circle direction must be +1 (ccw) or -1 (cw), got {direction}")
        return CirclePath(radius, x0, y0, direction, heading)
    if kind == "line":
        return LinePath(x0, y0, heading)
    raise ValueError(f"unknown path kind {kind!r}; expected one of {', '.join(PATH_KINDS)}")
