"""A robot that is not its nominal model, in its loop: the live run's sampled controller and a robot
that answers its commands late, as one vehicle a simulation can step.

A live run (bridge/live.py) controls a robot this way, once per communication step t_k:

1. it takes the newest pose of the robot (dead-reckoned from the pose's stamp to now);
2. it evaluates the guidance there and sends the wheel commands of eqs. 10-11 plus a push
   (``M3piDynamics.radio_command``), computed from its own speed setpoint V_s;
3. it advances its own states (V_s, and the wheel speeds its model predicts) over the step with the
   continuous model, the very ``VehicleStepper`` of an all-FMU run.

The robot applies each command ``command_latency`` after it was sent (the radio) and holds it until the
next one lands; its wheels follow with their own gains, dead-band, limit and lag
(``M3piDynamics.drive``). The motion capture stamps a pose ``pose_latency`` after the robot was there
(the latency a stamp does not show: bridge/mocap.py stamps a frame when the system hands it over), so
the pose the controller takes at t_k is the robot's pose at t_k - pose_latency, and what the run records
and tells the other vehicles of this robot is that pose too.

Seen through the motion capture, the robot is therefore one that runs pose_latency behind its true
self: its observed pose at t is its true pose at t - pose_latency, and a command sent at t_k moves the
observed robot from t_k + command_latency + pose_latency on. ``RobotLoopStepper`` integrates that
observed robot, so the two latencies add up in its motion (the delay D = command_latency +
pose_latency), and each step the controller sees the observed pose at t_k exactly: no pose history is
needed, and a delay that is no multiple of the step is exact (the robot's integration is split where a
command lands). Before the first command lands the robot stands on its mark; it then starts with the
wheel speeds it was given (the flying start of ``platoon m3pi-emulator``).

With both latencies 0 there is no such loop: the vehicle is the continuous ``VehicleStepper`` of every
run so far, whose wheel commands follow the guidance at every RK4 stage (fmus.model.factory chooses).
"""

from __future__ import annotations

import math

from .dynamics import M3piDynamics
from .integrate import integrate
from .vehicle import VehicleModel, VehicleStepper

M3PI_COMMAND_LATENCY = 0.0  # s, the nominal robot's radio: none
M3PI_POSE_LATENCY = 0.0  # s, the nominal robot's motion capture: none
# s: the longest latency a config or an FMU takes. A radio or a motion capture a second late is broken, not slow
# (an m3pi's XBee answers in a few ms, a motion capture in a few more), and a robot loop that late is not a platoon.
LATENCY_MAX = 1.0
COMMAND_FIELDS = 3  # a command in flight: (the instant it lands, right, left)
# the most commands in flight: a delay of ceil(D / step) + 1 steps (the C twin keeps them in a ring this long; the
# config says which latencies and step need more)
COMMAND_CAPACITY = 256


class RobotLoopStepper(VehicleStepper):
    """The live run's controller (this ``VehicleStepper``, its state) and the robot it drives (``robot``).

    ``state`` is the controller's: the observed pose (x, y, heading), the wheel speeds its model predicts
    and its speed setpoint V_s, as bridge/live.py keeps them; the outputs come from it, as the live run's
    do. ``robot`` is the observed robot (x, y, heading, v_right, v_left), moved by ``M3piDynamics.drive``
    under ``held`` (the command acting: right, left; empty before the first lands). ``commands`` holds
    the commands in flight, flat: (lands at, right, left) each, oldest first. Every attribute is a number
    or a list replaced (never changed in place) by a step, so a copy of ``vars`` restores a step.
    """

    def __init__(self, model: VehicleModel, coupling: str, max_substep: float, state: list[float], time: float,
                 command_latency: float, pose_latency: float):
        super().__init__(model, coupling, max_substep, state, time)
        self.delay = command_latency + pose_latency
        self.robot = list(state[:5])
        self.held: list[float] = []
        self.commands: list[float] = []

    def command(self, t: float, state: list[float]) -> tuple[float, float]:
        """The wheel commands the controller sends at t from ``state`` (bridge/live.py's step)."""
        dynamics = self.model.dynamics
        assert isinstance(dynamics, M3piDynamics)
        _, acceleration, _ = self.evaluate(t, state)
        return dynamics.radio_command(state[5], acceleration, self.added_speed)

    def step(self, t: float, h: float) -> None:
        """Send the command of t, advance the controller and the robot to t + h, and measure the robot there."""
        right, left = self.command(t, self.state)
        commands = self.commands + [t + self.delay, right, left]
        if len(commands) > COMMAND_CAPACITY * COMMAND_FIELDS:
            raise ValueError(f"more than {COMMAND_CAPACITY} commands in flight (the latencies span too many steps)")
        controller = integrate(self.derivative, t, self.state, h, self.max_substep)
        self.check(controller, t + h)
        robot, held, commands = self.move_robot(t, h, commands)
        if not all(math.isfinite(v) for v in robot):
            raise ValueError(f"the robot's state became non-finite before t = {t + h:.6g} s")
        self.robot, self.held, self.commands = robot, held, commands
        self.state = robot[:3] + controller[3:]
        self.time = t + h

    def move_robot(self, t: float, h: float, commands: list[float]) -> tuple[list[float], list[float], list[float]]:
        """The robot over [t, t + h]: (its state at t + h, the command then acting, the commands still in flight).

        Each command acts from the instant it lands (exactly: the integration stops there and goes on
        with it); a robot that no command reached yet stands still."""
        robot, held, now, end = self.robot, self.held, t, t + h
        while True:
            lands = commands[0] if commands else math.inf
            until = min(lands, end)
            if held and until > now:
                robot = integrate(self.robot_derivative(held), now, robot, until - now, self.max_substep)
            now = max(now, until)
            if lands > end:
                return robot, held, commands
            held, commands = commands[1:COMMAND_FIELDS], commands[COMMAND_FIELDS:]

    def robot_derivative(self, held: list[float]):
        """The robot's own physics under the command ``held`` (right, left): ``M3piDynamics.drive``, no push
        (a push reaches the robot in its commands, as in a live run)."""
        dynamics = self.model.dynamics
        assert isinstance(dynamics, M3piDynamics)
        right_cmd, left_cmd = held

        def derivative(_t: float, s: list[float]) -> list[float]:
            return dynamics.drive(s[2], s[3], s[4], right_cmd, left_cmd, 0.0)

        return derivative
