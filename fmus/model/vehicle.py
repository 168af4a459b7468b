"""One platoon vehicle: guidance on top of dynamics, and its life between communication points.

``VehicleModel`` is the vehicle's right-hand side: given its own state, where its target is, how
the vehicle behind it is doing and (acc, cacc) where its on-board sensor sees the vehicle ahead, it
returns the state derivative. The FMU, the monolithic reference
and the live-robot bridge all call this one function.

``VehicleStepper`` is what an FMU instance holds: the state, the latest input samples, and the
coupling mode that decides how those samples are seen inside a step (see ``coupling``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

from .coupling import arc_extrapolate, linear_extrapolate
from .dynamics import Dynamics
from .guidance import (
    SENSING_LAWS,
    cacc_acceleration,
    distance,
    lateral_acceleration,
    line_of_sight,
    spacing_error,
    spacing_speed,
    speed_for_acceleration,
    time_gap_speed,
)
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
    "sensor.x": "sensor_x",
    "sensor.y": "sensor_y",
    "sensor.heading": "sensor_heading",
    "sensor.speed": "sensor_speed",
    "sensor.speed_rate": "sensor_speed_rate",
    "sensor.turn_rate": "sensor_turn_rate",
    "sensor.time": "sensor_time",
    "disturbance.lateral_acceleration": "added_acceleration",
    "disturbance.speed": "added_speed",
}


@dataclass(frozen=True)
class SpeedLaw:
    """Which speed law commands the vehicle (``guidance.SPEED_LAWS``) and its parameters.

    ``time_gap`` h (s), ``standstill_gap`` r (m) and ``gain`` k_p (1/s) act only under acc and cacc.
    """

    kind: str = "paper"
    time_gap: float = 0.0
    standstill_gap: float = 0.0
    gain: float = 0.0
    # True when the law reads the gap to the vehicle ahead from the on-board sensor (a field, not a
    # property: the right-hand side asks at every evaluation)
    senses: bool = field(init=False)

    def __post_init__(self) -> None:
        object.__setattr__(self, "senses", self.kind in SENSING_LAWS)


PAPER_LAW = SpeedLaw()


@dataclass(frozen=True)
class VehicleModel:
    """Guidance law, spacing and speed loop of one vehicle, on top of its dynamics."""

    law: str
    d_star: float
    speed_command: float  # V_c, used when the vehicle is last (paper's law)
    is_last: bool
    dynamics: Dynamics
    speed_law: SpeedLaw = PAPER_LAW

    def sensing_speed(self, state: list[float], speed: float, sensed_gap: float, predecessor_speed: float) -> float:
        """V_cmd of the laws that read the on-board sensor: acc, or cacc (which also reads the vehicle
        ahead's communicated speed)."""
        law = self.speed_law
        if law.kind == "acc":
            return time_gap_speed(sensed_gap, law.standstill_gap, law.time_gap)
        error = spacing_error(sensed_gap, law.standstill_gap, law.time_gap, speed)
        acceleration = cacc_acceleration(predecessor_speed, speed, error, law.time_gap, law.gain)
        return speed_for_acceleration(self.dynamics.loop_speed(state), acceleration, self.dynamics.k_v)

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
        target_speed: float = 0.0,
        sensor_x: float = 0.0,
        sensor_y: float = 0.0,
    ) -> tuple[list[float], float, float]:
        """State derivative, acting lateral acceleration and distance to the target.

        ``target_speed`` is the vehicle ahead's speed as communicated (cacc); ``sensor_x``, ``sensor_y``
        its position as the on-board sensor measures it (acc, cacc). The paper's law reads neither.
        """
        x, y, heading = self.dynamics.pose(state)
        speed = self.dynamics.speed(state, added_speed)
        target_distance, los = line_of_sight(x, y, target_x, target_y)
        acceleration = (
            lateral_acceleration(self.law, speed, target_distance, los, heading, target_heading) + added_acceleration
        )
        if self.speed_law.senses:
            commanded = self.sensing_speed(state, speed, distance(x, y, sensor_x, sensor_y), target_speed)
        elif self.is_last:
            commanded = self.speed_command
        else:
            commanded = spacing_speed(follower_speed, follower_gap, self.d_star)
        return self.dynamics.derivative(state, acceleration, commanded, added_speed), acceleration, target_distance


class VehicleStepper:
    """A vehicle between communication points: state, latest input samples, coupling mode.

    Input samples are plain attributes the FMU wrapper writes; ``*_time`` says which instant the
    sender's values describe.
    """

    def __init__(self, model: VehicleModel, coupling: str, max_substep: float, state: list[float], time: float):
        self.model = model
        self.senses = model.speed_law.senses
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
        # sensor (acc, cacc): the vehicle ahead's motion as the on-board sensor measures it
        self.sensor_x = self.sensor_y = self.sensor_heading = 0.0
        self.sensor_speed = self.sensor_speed_rate = self.sensor_turn_rate = self.sensor_time = 0.0
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

    def sensor_at(self, t: float) -> tuple[float, float]:
        """Position of the vehicle ahead at time t as the on-board sensor sees it (extrapolated as the
        target is: the sensor's heading, speed and rates only serve that)."""
        if not self.extrapolate:
            return self.sensor_x, self.sensor_y
        x, y, _, _ = arc_extrapolate(
            self.sensor_x,
            self.sensor_y,
            self.sensor_heading,
            self.sensor_speed,
            self.sensor_speed_rate,
            self.sensor_turn_rate,
            t - self.sensor_time,
        )
        return x, y

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
        tx, ty, th, tv = self.target_at(t)
        follower_speed, follower_gap = self.follower_at(t)
        if not self.senses:
            return self.model.evaluate(
                state, tx, ty, th, follower_speed, follower_gap, self.added_acceleration, self.added_speed
            )
        sx, sy = self.sensor_at(t)
        return self.model.evaluate(
            state, tx, ty, th, follower_speed, follower_gap, self.added_acceleration, self.added_speed, tv, sx, sy
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
