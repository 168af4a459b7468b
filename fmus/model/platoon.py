"""The whole platoon as one system: the monolithic reference and the linearization's right-hand side.

The same steppers the FMUs hold are evaluated with exact, same-instant neighbour values, so the
platoon's right-hand side is the FMUs' right-hand side without any coupling error. Integrating it with
one RK4 over every state gives the yardstick a co-simulation is measured against.

State layout: [s] + vehicle 1 state + ... + vehicle N state, where s is the target's arc length.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

from .integrate import integrate
from .target import VirtualTargetStepper
from .vehicle import VehicleStepper


@dataclass
class PlatoonSystem:
    """A virtual target and N vehicle steppers, coupled instantaneously.

    ``speed_chain_gap`` chooses which gap enters vehicle i's speed command: "follower" (d_{i+1}, the
    paper's linearization and our FMUs) or "own" (d_i, as the paper's text prints it), for analysis.
    """

    target: VirtualTargetStepper
    vehicles: list[VehicleStepper]
    speed_chain_gap: str = "follower"
    offsets: list[int] = field(init=False)

    def __post_init__(self) -> None:
        self.offsets = [1]
        for vehicle in self.vehicles:
            self.offsets.append(self.offsets[-1] + len(vehicle.state))

    def initial_state(self) -> list[float]:
        y = [self.target.arc_length]
        for vehicle in self.vehicles:
            y += list(vehicle.state)
        return y

    def split(self, y: list[float]) -> list[list[float]]:
        return [y[self.offsets[i] : self.offsets[i + 1]] for i in range(len(self.vehicles))]

    def _share_samples(self, t: float, y: list[float]) -> list[list[float]]:
        """Give every stepper its neighbours' values at the same instant t (no extrapolation needed)."""
        states = self.split(y)
        poses = []
        speeds = []
        for vehicle, state in zip(self.vehicles, states):
            dynamics = vehicle.model.dynamics
            poses.append(dynamics.pose(state))
            speeds.append(dynamics.speed(state, vehicle.added_speed))
        target = self.target
        tx, ty, th = target.path.pose_at(y[0])
        gaps = []
        ahead = (tx, ty)
        for pose in poses:
            gaps.append(math.hypot(ahead[0] - pose[0], ahead[1] - pose[1]))
            ahead = pose
        target.lead_speed, target.lead_gap, target.lead_time = speeds[0], gaps[0], t
        target_speed = target.speed_of(speeds[0], gaps[0])  # acc, cacc: V_c (plus a push on the target)
        ahead_pose, ahead_speed = (tx, ty, th), target_speed
        n = len(self.vehicles)
        for i, vehicle in enumerate(self.vehicles):
            vehicle.target_x, vehicle.target_y, vehicle.target_heading = ahead_pose
            vehicle.target_speed, vehicle.target_time = ahead_speed, t
            # the on-board sensor (acc, cacc) sees the same instant's pose: nothing to extrapolate
            vehicle.sensor_x, vehicle.sensor_y, vehicle.sensor_heading = ahead_pose
            vehicle.sensor_speed, vehicle.sensor_time = ahead_speed, t
            if i + 1 < n:
                vehicle.follower_speed = speeds[i + 1]
                vehicle.follower_gap = gaps[i + 1] if self.speed_chain_gap == "follower" else gaps[i]
                vehicle.follower_time = t
            ahead_pose, ahead_speed = poses[i], speeds[i]
        return states

    def derivative(self, t: float, y: list[float]) -> list[float]:
        states = self._share_samples(t, y)
        dy = [self.target.speed_at(t)]
        for vehicle, state in zip(self.vehicles, states):
            dy += vehicle.derivative(t, state)
        return dy

    def outputs(self, t: float, y: list[float]) -> list[dict[str, float]]:
        """Every component's FMU outputs at (t, y): target first, then vehicles 1..N."""
        states = self._share_samples(t, y)
        self.target.arc_length, self.target.time = y[0], t
        vehicle_outputs = []
        for vehicle, state in zip(self.vehicles, states):
            vehicle.state, vehicle.time = state, t
            vehicle_outputs.append(vehicle.outputs())
        # Rates the target reports are the lead's own rates, known only after the lead's outputs.
        self.target.lead_speed_rate = vehicle_outputs[0]["speed_rate"]
        self.target.lead_gap_rate = vehicle_outputs[0]["gap_rate"]
        return [self.target.outputs()] + vehicle_outputs

    def set_disturbances(self, disturbances: list[tuple[float, float]], target_speed: float = 0.0) -> None:
        """(added lateral acceleration, added speed) per vehicle, and the speed added to the target's, held
        until changed."""
        self.target.added_speed = target_speed
        for vehicle, (acceleration, speed) in zip(self.vehicles, disturbances):
            vehicle.added_acceleration, vehicle.added_speed = acceleration, speed

    def advance(self, t: float, y: list[float], step: float, max_substep: float) -> list[float]:
        """Integrate from t to t + step; raises ValueError naming the vehicle if its motion breaks down."""
        y = integrate(self.derivative, t, y, step, max_substep)
        for index, (vehicle, state) in enumerate(zip(self.vehicles, self.split(y)), start=1):
            try:
                vehicle.check(state, t + step)
            except ValueError as error:
                raise ValueError(f"vehicle{index}: {error}") from None
        return y
