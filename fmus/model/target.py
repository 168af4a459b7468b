"""The virtual target: a point that moves along the path at the speed that restores spacing.

Only the lead vehicle's target knows the path. Its state is its arc length s along the path; it moves
at V_0 = V_1 d*/d_1 (eq. 3), where V_1 is the lead vehicle's speed and d_1 the lead's distance to the
target (velocity information flowing forward). Under the acc and cacc speed laws (the lead vehicle's
law; ``guidance.SENSING_LAWS``) it needs no forward information: it moves at the constant V_c.

A speed push (``added_speed``, the ``disturbance.speed`` input) is added to whatever speed the law gives,
as a vehicle's is added to its speed over ground: under acc and cacc the head of the platoon then moves at
exactly V_c plus the push, a clean, prescribed speed for the vehicles behind to follow. Its rate is not in
``speed_rate`` (a push is held over each step, a vehicle's too).
"""

from __future__ import annotations

import math

from .coupling import linear_extrapolate
from .guidance import SENSING_LAWS, spacing_speed, spacing_speed_rate
from .integrate import integrate
from .paths import Path


class VirtualTargetStepper:
    """The target between communication points: arc length, latest lead samples, coupling mode."""

    def __init__(self, path: Path, d_star: float, coupling: str, max_substep: float, arc_length: float, time: float,
                 speed_law: str = "paper", speed_command: float = 0.0):
        self.path = path
        self.d_star = d_star
        # acc, cacc: the target moves at the constant V_c (speed_command); paper: at V_1 d*/d_1
        self.constant_speed = speed_law in SENSING_LAWS
        self.speed_command = speed_command
        self.extrapolate = coupling == "extrapolate"
        self.max_substep = max_substep
        self.arc_length = arc_length
        self.time = time
        self.lead_speed = 1.0
        self.lead_gap = d_star
        self.lead_speed_rate = self.lead_gap_rate = self.lead_time = 0.0
        self.added_speed = 0.0  # a speed push, held over the step

    def lead_at(self, t: float) -> tuple[float, float, float, float]:
        """Lead speed, gap and their rates at time t as the target sees them."""
        if not self.extrapolate:
            return self.lead_speed, self.lead_gap, self.lead_speed_rate, self.lead_gap_rate
        dt = t - self.lead_time
        return (
            linear_extrapolate(self.lead_speed, self.lead_speed_rate, dt),
            linear_extrapolate(self.lead_gap, self.lead_gap_rate, dt),
            self.lead_speed_rate,
            self.lead_gap_rate,
        )

    def speed_at(self, t: float) -> float:
        if self.constant_speed:
            return self.speed_of(0.0, 0.0)
        speed, gap, _, _ = self.lead_at(t)
        return self.speed_of(speed, gap)

    def speed_of(self, lead_speed: float, lead_gap: float) -> float:
        """The target's speed from the lead's speed and gap as it sees them (unused under acc and cacc),
        plus the push. Adding a zero push leaves every bit of an undisturbed run as it was."""
        law_speed = self.speed_command if self.constant_speed else spacing_speed(lead_speed, lead_gap, self.d_star)
        return law_speed + self.added_speed

    def derivative(self, t: float, state: list[float]) -> list[float]:
        return [self.speed_at(t)]

    def step(self, t: float, h: float) -> None:
        (arc_length,) = integrate(self.derivative, t, [self.arc_length], h, self.max_substep)
        if not math.isfinite(arc_length):
            raise ValueError(f"the target's arc length became non-finite during the step from t = {t:.6g} s")
        self.arc_length = arc_length
        self.time = t + h

    def outputs(self) -> dict[str, float]:
        t = self.time
        if self.constant_speed:
            target_speed, target_speed_rate = self.speed_of(0.0, 0.0), 0.0
        else:
            speed, gap, speed_rate, gap_rate = self.lead_at(t)
            target_speed = self.speed_of(speed, gap)
            target_speed_rate = spacing_speed_rate(speed, speed_rate, gap, gap_rate, self.d_star)
        x, y, heading = self.path.pose_at(self.arc_length)
        curvature = self.path.curvature(self.arc_length)
        return {
            "x": x,
            "y": y,
            "heading": heading,
            "speed": target_speed,
            "speed_rate": target_speed_rate,
            "turn_rate": target_speed * curvature,
            "curvature": curvature,
            "arc_length": self.arc_length,
            "output_time": t,
        }
