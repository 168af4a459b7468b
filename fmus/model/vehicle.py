"""One platoon vehicle: guidance on top of dynamics, and its life between communication points.

``VehicleModel`` is the vehicle's right-hand side: given its own state, where its target is and how
the vehicle behind it is doing, it returns the state derivative. The FMU, the monolithic reference
and the live-robot bridge all call this one function.

``VehicleStepper`` is what an FMU instance holds: the state, the latest input samples, and the
coupling mode that decides how those samples are seen inside a step (see ``coupling``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from .coupling import arc_extrapolate, linear_extrapolate
from .dynamics import Dynamics
from .guidance import lateral_acceleration, line_of_sight, spacing_speed
from .integrate import integrate


# Each public input of a vehicle (the Vehicle FMU's input names, Fig. 2's signals) and the
# ``VehicleStepper`` attribute it sets. The FMU slave and the live-robot bridge both set inputs by it.
VEHICLE_INPUTS = {
    "target.x": "target_x",
    "target.y": "target_y",
    "target.heading": "target_heading",
    "target.speed": "target_speed",
    "target.speed_rate": "target_speed_rate",
    "target.turn_rate": "target_turn_rate",
    "target.time": "target_time",
    "follower.speed": "follower_speed",
    "follower.gap": "follower_gap",
    "follower.speed_rate": "follower_speed_rate",
    "follower.gap_rate": "follower_gap_rate",
    "follower.time": "follower_time",
    "disturbance.lateral_acceleration": "added_acceleration",
    "disturbance.speed": "added_speed",
}


@dataclass(frozen=True)
class VehicleModel:
    """Guidance law, spacing and speed loop of one vehicle, on top of its dynamics."""

    law: str
    d_star: float
    speed_command: float  # V_c, used when the vehicle is last
    is_last: bool
    dynamics: Dynamics

    def evaluate(
        self,
        state: list[float],
        target_x: float,
        target_y: float,
        target_heading: float,
        follower_speed: float,
        follower_gap: float,
        added_acceleration: float,
        added_speed: float,
    ) -> tuple[list[float], float, float]:
        """State derivative, acting lateral acceleration and distance to the target."""
        x, y, heading = self.dynamics.pose(state)
        speed = self.dynamics.speed(state, added_speed)
        distance, los = line_of_sight(x, y, target_x, target_y)
        acceleration = (
            lateral_acceleration(self.law, speed, distance, los, heading, target_heading) + added_acceleration
        )
        if self.is_last:
            commanded = self.speed_command
        else:
            commanded = spacing_speed(follower_speed, follower_gap, self.d_star)
        return self.dynamics.derivative(state, acceleration, commanded, added_speed), acceleration, distance


class VehicleStepper:
    """A vehicle between communication points: state, latest input samples, coupling mode.

    Input samples are plain attributes the FMU wrapper writes; ``*_time`` says which instant the
    sender's values describe.
    """

    def __init__(self, model: VehicleModel, coupling: str, max_substep: float, state: list[float], time: float):
        self.model = model
        self.extrapolate = coupling == "extrapolate"
        self.max_substep = max_substep
        self.state = state
        self.time = time
        # target (the vehicle ahead, or the virtual target): lateral information
        self.target_x = self.target_y = self.target_heading = 0.0
        self.target_speed = self.target_speed_rate = self.target_turn_rate = self.target_time = 0.0
        # follower (the vehicle behind): velocity information
        self.follower_speed = self.follower_gap = 1.0
        self.follower_speed_rate = self.follower_gap_rate = self.follower_time = 0.0
        # disturbances, held over the step
        self.added_acceleration = self.added_speed = 0.0

    def target_at(self, t: float) -> tuple[float, float, float, float]:
        """Target pose and speed at time t as this vehicle sees it."""
        if not self.extrapolate:
            return self.target_x, self.target_y, self.target_heading, self.target_speed
        return arc_extrapolate(
            self.target_x,
            self.target_y,
            self.target_heading,
            self.target_speed,
            self.target_speed_rate,
            self.target_turn_rate,
            t - self.target_time,
        )

    def follower_at(self, t: float) -> tuple[float, float]:
        """Speed and gap of the vehicle behind at time t as this vehicle sees them."""
        if not self.extrapolate:
            return self.follower_speed, self.follower_gap
        dt = t - self.follower_time
        return (
            linear_extrapolate(self.follower_speed, self.follower_speed_rate, dt),
            linear_extrapolate(self.follower_gap, self.follower_gap_rate, dt),
        )

    def evaluate(self, t: float, state: list[float]) -> tuple[list[float], float, float]:
        tx, ty, th, _ = self.target_at(t)
        follower_speed, follower_gap = self.follower_at(t)
        return self.model.evaluate(
            state, tx, ty, th, follower_speed, follower_gap, self.added_acceleration, self.added_speed
        )

    def derivative(self, t: float, state: list[float]) -> list[float]:
        return self.evaluate(t, state)[0]

    def check(self, state: list[float], time: float) -> None:
        """Raise ValueError with the reason if ``state`` at ``time`` cannot go on (guidance needs V > 0)."""
        if not all(math.isfinite(v) for v in state):
            raise ValueError(f"the state became non-finite before t = {time:.6g} s")
        speed = self.model.dynamics.speed(state, self.added_speed)
        if speed <= 0.0:
            raise ValueError(f"speed fell to {speed:.6g} m/s at t = {time:.6g} s; guidance needs V > 0")

    def step(self, t: float, h: float) -> None:
        """Advance from t to t + h; raises ValueError with the reason if the motion breaks down."""
        state = integrate(self.derivative, t, self.state, h, self.max_substep)
        self.check(state, t + h)
        self.state = state
        self.time = t + h

    def outputs(self) -> dict[str, float]:
        """Every output at the current time, from the state and the inputs seen at that time."""
        t = self.time
        dynamics = self.model.dynamics
        state = self.state
        derivative, acceleration, gap = self.evaluate(t, state)
        x, y, heading = dynamics.pose(state)
        speed = dynamics.speed(state, self.added_speed)
        tx, ty, th, tv = self.target_at(t)
        dx, dy = tx - x, ty - y
        relative_vx = tv * math.cos(th) - speed * math.cos(heading)
        relative_vy = tv * math.sin(th) - speed * math.sin(heading)
        wheel_right, wheel_left = dynamics.wheel_speeds(state, acceleration, self.added_speed)
        return {
            "x": x,
            "y": y,
            "heading": heading,
            "speed": speed,
            "speed_rate": dynamics.speed_rate(derivative),
            "turn_rate": dynamics.heading_rate(derivative),
            "lateral_acceleration": acceleration,
            "gap": gap,
            "gap_rate": (dx * relative_vx + dy * relative_vy) / gap,
            "wheel.right": wheel_right,
            "wheel.left": wheel_left,
            "output_time": t,
        }
