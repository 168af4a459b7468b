"""Vehicle dynamics: how a lateral-acceleration command and a speed command move a vehicle.

Two models share one interface (state layout, ``derivative``, ``pose``, ``speed``) so a vehicle can
switch between them by a parameter:

* ``KinematicDynamics``: the paper's vehicle. State (x, y, heading, V); heading rate a/V; first-order
  speed loop dV/dt = k_v (V_cmd - V).
* ``M3piDynamics``: a Pololu m3pi differential drive. The speed loop runs in the controller (state
  V_s), the lateral command is mapped to wheel speeds by the paper's eqs. 10-11, the wheel speeds are
  limited and follow their commands with a first-order motor lag, and the body moves as a unicycle
  driven by the two wheels. State (x, y, heading, v_right, v_left, V_s).

Disturbances enter as the paper describes them: an added lateral acceleration (added to the command
before it acts) and an added speed (the vehicle moves that much faster over ground than its speed
state, for as long as the disturbance lasts; the speed loop does not see it).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from .guidance import speed_loop

DYNAMICS_KINDS = ("kinematic", "m3pi")

# Pololu m3pi (3pi base) constants. The 3pi is 9.5 cm across and its wheels (17 mm radius, per the
# 3pi User's Guide) sit inside that disc; Pololu does not publish the wheel track, so we estimate it
# from the body: about 84 mm between wheel centres (95 mm body minus two ~6 mm half-wheel widths and
# clearance). Top speed with the stock 30:1 motors is about 1 m/s. The motor time constant is an
# estimate for small gear motors under load (tens of milliseconds). Wheel speeds are linear (m/s);
# divide by the 17 mm radius for rad/s.
M3PI_TRACK = 0.084
M3PI_WHEEL_SPEED_MAX = 1.0
M3PI_MOTOR_TIME_CONSTANT = 0.05
# A real robot is not its nominal model: each wheel answers a command with its own gain (wheel speed per
# commanded speed; motor and gearbox spread), and a command below the dead-band does not turn the wheel at
# all (static friction). The nominal robot has gains of 1 and no dead-band; `platoon calibrate` identifies them.
M3PI_WHEEL_GAIN = 1.0
M3PI_WHEEL_DEADBAND = 0.0


def differential_wheel_speeds(speed: float, lateral_acceleration: float, track: float) -> tuple[float, float]:
    """Right and left wheel speeds realising a turn of radius R_t = V^2/a (paper eqs. 10-11).

    V_r = V (1 + W/(2 R_t)) and V_l = V (1 - W/(2 R_t)); written with a = V^2/R_t so that a = 0
    (straight ahead, R_t infinite) needs no special case.
    """
    half_difference = 0.5 * track * lateral_acceleration / speed
    return speed + half_difference, speed - half_difference


@dataclass(frozen=True)
class KinematicDynamics:
    """The paper's kinematic vehicle (x, y, heading, speed), with an optional speed limit: ``speed_max`` > 0 clips
    the speed loop's command to +-speed_max, as an m3pi's wheels clip theirs (``M3piDynamics.limit_wheels``), so a
    vehicle started below it stays below it. 0 (the default) is no limit: the command is used as it is, to the bit."""

    k_v: float
    track: float = M3PI_TRACK  # only used to report equivalent wheel speeds
    speed_max: float = 0.0  # m/s; 0: no limit

    kind = "kinematic"
    state_names = ("x", "y", "heading", "speed")

    def initial_state(self, x: float, y: float, heading: float, speed: float) -> list[float]:
        return [x, y, heading, speed]

    def pose(self, state: list[float]) -> tuple[float, float, float]:
        return state[0], state[1], state[2]

    def speed(self, state: list[float], speed_offset: float) -> float:
        return state[3] + speed_offset

    @staticmethod
    def loop_speed(state: list[float]) -> float:
        """The speed the speed loop regulates (its state; a disturbance's added speed is not in it)."""
        return state[3]

    def derivative(
        self, state: list[float], lateral_acceleration: float, commanded_speed: float, speed_offset: float
    ) -> list[float]:
        heading = state[2]
        v = state[3] + speed_offset
        return [
            v * math.cos(heading),
            v * math.sin(heading),
            lateral_acceleration / v,
            speed_loop(self.k_v, self.limit_command(commanded_speed), state[3]),
        ]

    def limit_command(self, commanded_speed: float) -> float:
        """The speed command as the vehicle can follow it: clipped to +-speed_max, or as it is without a limit."""
        limit = self.speed_max
        if limit <= 0.0:
            return commanded_speed
        return min(max(commanded_speed, -limit), limit)

    @staticmethod
    def heading_rate(derivative: list[float]) -> float:
        return derivative[2]

    @staticmethod
    def speed_rate(derivative: list[float]) -> float:
        return derivative[3]

    def wheel_speeds(self, state: list[float], lateral_acceleration: float, speed_offset: float) -> tuple[float, float]:
        return differential_wheel_speeds(state[3] + speed_offset, lateral_acceleration, self.track)


@dataclass(frozen=True)
class M3piDynamics:
    """A Pololu m3pi: speed loop in the controller, eqs. 10-11 to wheels, limits, motor lag, unicycle."""

    k_v: float
    track: float = M3PI_TRACK
    wheel_speed_max: float = M3PI_WHEEL_SPEED_MAX
    motor_time_constant: float = M3PI_MOTOR_TIME_CONSTANT
    wheel_gain_right: float = M3PI_WHEEL_GAIN
    wheel_gain_left: float = M3PI_WHEEL_GAIN
    wheel_deadband: float = M3PI_WHEEL_DEADBAND

    kind = "m3pi"
    state_names = ("x", "y", "heading", "wheel_right", "wheel_left", "speed_setpoint")

    def initial_state(self, x: float, y: float, heading: float, speed: float) -> list[float]:
        return [x, y, heading, speed, speed, speed]

    def pose(self, state: list[float]) -> tuple[float, float, float]:
        return state[0], state[1], state[2]

    def speed(self, state: list[float], speed_offset: float) -> float:
        return 0.5 * (state[3] + state[4]) + speed_offset

    @staticmethod
    def loop_speed(state: list[float]) -> float:
        """The speed the controller's speed loop regulates: its setpoint V_s."""
        return state[5]

    def wheel_commands(self, setpoint: float, lateral_acceleration: float) -> tuple[float, float]:
        """Wheel speed commands from eqs. 10-11, clipped to the motors' limits."""
        right, left = differential_wheel_speeds(setpoint, lateral_acceleration, self.track)
        return self.limit_wheels(right, left)

    def limit_wheels(self, right: float, left: float) -> tuple[float, float]:
        """Wheel speed commands as the motors can follow them: clipped to +-wheel_speed_max."""
        limit = self.wheel_speed_max
        return min(max(right, -limit), limit), min(max(left, -limit), limit)

    def radio_command(self, setpoint: float, lateral_acceleration: float, added_speed: float) -> tuple[float, float]:
        """The wheel commands a controller sends the robot: eqs. 10-11 from the speed setpoint and the lateral
        command, plus a speed disturbance's push (it moves the robot faster; the speed loop does not see it),
        clipped to the motors' limits. The live run (bridge/live.py) and the sampled robot loop
        (fmus.model.robot_loop) both send this."""
        right, left = self.wheel_commands(setpoint, lateral_acceleration)
        return self.limit_wheels(right + added_speed, left + added_speed)

    def wheel_target(self, command: float, gain: float) -> float:
        """The speed a wheel heads for under a speed command: none inside the dead-band, else the wheel's
        gain times the command, and never beyond the motor's limit.

        With the nominal gain of 1 and no dead-band this is the command clipped to +-wheel_speed_max,
        exactly (1.0 * c == c), so a nominal robot moves as it always has, to the bit.
        """
        if abs(command) < self.wheel_deadband:
            return 0.0
        limit = self.wheel_speed_max
        return min(max(gain * command, -limit), limit)

    def drive(
        self, heading: float, right: float, left: float, right_cmd: float, left_cmd: float, speed_offset: float
    ) -> list[float]:
        """The robot's own physics: derivative of (x, y, heading, v_right, v_left) under wheel commands.

        Each wheel heads for its target (``wheel_target``: dead-band, gain, limit) with the first-order
        motor lag; the body moves as a unicycle driven by the two wheels. The FMU's model and the m3pi
        emulator (bridge/emulator.py) both move a robot with this one function: the emulator with the
        commands it receives over Zenoh, and its robot's own truth in place of the nominal constants.
        """
        v = 0.5 * (right + left) + speed_offset
        lag = 1.0 / self.motor_time_constant
        right_target = self.wheel_target(right_cmd, self.wheel_gain_right)
        left_target = self.wheel_target(left_cmd, self.wheel_gain_left)
        return [
            v * math.cos(heading),
            v * math.sin(heading),
            (right - left) / self.track,
            (right_target - right) * lag,
            (left_target - left) * lag,
        ]

    def derivative(
        self, state: list[float], lateral_acceleration: float, commanded_speed: float, speed_offset: float
    ) -> list[float]:
        setpoint = state[5]
        right_cmd, left_cmd = self.wheel_commands(setpoint, lateral_acceleration)
        derivative = self.drive(state[2], state[3], state[4], right_cmd, left_cmd, speed_offset)
        derivative.append(speed_loop(self.k_v, commanded_speed, setpoint))
        return derivative

    @staticmethod
    def heading_rate(derivative: list[float]) -> float:
        return derivative[2]

    @staticmethod
    def speed_rate(derivative: list[float]) -> float:
        return 0.5 * (derivative[3] + derivative[4])

    def wheel_speeds(self, state: list[float], lateral_acceleration: float, speed_offset: float) -> tuple[float, float]:
        return state[3] + speed_offset, state[4] + speed_offset


Dynamics = KinematicDynamics | M3piDynamics


def make_dynamics(
    kind: str,
    k_v: float,
    track: float = M3PI_TRACK,
    wheel_speed_max: float = M3PI_WHEEL_SPEED_MAX,
    motor_time_constant: float = M3PI_MOTOR_TIME_CONSTANT,
    wheel_gain_right: float = M3PI_WHEEL_GAIN,
    wheel_gain_left: float = M3PI_WHEEL_GAIN,
    wheel_deadband: float = M3PI_WHEEL_DEADBAND,
    speed_max: float = 0.0,
) -> Dynamics:
    """``speed_max``: the kinematic vehicle's speed limit (0: none); an m3pi is bounded by its wheels."""
    if kind == "kinematic":
        return KinematicDynamics(k_v, track, speed_max)
    if kind == "m3pi":
        return M3piDynamics(k_v, track, wheel_speed_max, motor_time_constant, wheel_gain_right, wheel_gain_left,
                            wheel_deadband)
    raise ValueError(f"unknown dynamics {kind!r}; expected one of {', '.join(DYNAMICS_KINDS)}")
