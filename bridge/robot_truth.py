"""What a robot really is, on the robot side only: the file the m3pi emulator reads, and the run never does.

A real m3pi is not its model: its wheels answer a command with their own gains, its motors lag by their
own time constant and saturate at their own limit, small commands do not turn the wheels (a dead-band),
the radio delays every command and the motion capture every pose, and the poses are noisy. The
emulator (``platoon m3pi-emulator --robots TRUTH.toml``) takes each robot's truth from a TOML file::

    [default]                  # every robot, unless its own table says otherwise
    position_noise = 0.002     # m, standard deviation per axis
    heading_noise = 0.035      # rad

    [robots.3]                 # robot id 3 (its id on Zenoh, not the vehicle number)
    wheel_gain_right = 1.08
    wheel_gain_left = 0.93
    motor_time_constant = 0.09
    wheel_speed_max = 0.8
    wheel_deadband = 0.02      # m/s
    command_latency = 0.025    # s, command received -> applied (the radio)
    pose_latency = 0.008       # s, robot there -> pose stamped and handed over (the motion capture)

``pose_latency`` is the motion capture's latency that its stamps do not show (as ``platoon mocap`` stamps a
frame when the system hands it over): the pose is the robot's pose that long before its stamp, the meaning of
the model's ``[m3pi] pose_latency``. A key left out is the model's value (the config's ``[m3pi]`` table, or the emulator's command-line
settings for latencies and noise). The keys are those of ``platoon calibrate``'s output (the ``[m3pi]``
keys), plus the two noises, so that a calibration can be checked against the truth it should find.
"""

from __future__ import annotations

import math
import tomllib
from dataclasses import dataclass, fields, replace
from pathlib import Path
from typing import Any

from fmus.model.dynamics import M3piDynamics

# the robot's physics, as M3piDynamics names them (and as a config's [m3pi] table does)
DYNAMICS_KEYS = ("track", "wheel_speed_max", "motor_time_constant", "wheel_gain_right", "wheel_gain_left",
                 "wheel_deadband")
LINK_KEYS = ("command_latency", "pose_latency")  # s: the radio, the motion capture
NOISE_KEYS = ("position_noise", "heading_noise")  # m, rad
TRUTH_KEYS = DYNAMICS_KEYS + LINK_KEYS + NOISE_KEYS
POSITIVE = {"track", "wheel_speed_max", "motor_time_constant", "wheel_gain_right", "wheel_gain_left"}


class TruthError(ValueError):
    """A robot truth file that cannot be used (the message names the file, the table and the key)."""


@dataclass(frozen=True)
class RobotTruth:
    """One robot's truth; None: the model's value (or the emulator's global setting)."""

    track: float | None = None
    wheel_speed_max: float | None = None
    motor_time_constant: float | None = None
    wheel_gain_right: float | None = None
    wheel_gain_left: float | None = None
    wheel_deadband: float | None = None
    command_latency: float | None = None
    pose_latency: float | None = None
    position_noise: float | None = None
    heading_noise: float | None = None

    def dynamics(self, model: M3piDynamics) -> M3piDynamics:
        """The model's m3pi with this robot's own physics where the truth sets it."""
        changes = {key: getattr(self, key) for key in DYNAMICS_KEYS if getattr(self, key) is not None}
        return replace(model, **changes)

    def merged(self, other: RobotTruth) -> RobotTruth:
        """This truth with ``other``'s set values on top."""
        return replace(self, **{f.name: getattr(other, f.name) for f in fields(other) if getattr(other, f.name) is not None})


@dataclass(frozen=True)
class TruthFile:
    """The truths of a file: a default and one per robot id."""

    default: RobotTruth
    robots: dict[int, RobotTruth]

    def robot(self, robot: int) -> RobotTruth:
        return self.default.merged(self.robots.get(robot, RobotTruth()))


def _truth(table: Any, where: str) -> RobotTruth:
    if not isinstance(table, dict):
        raise TruthError(f"{where}: expected a table of {', '.join(TRUTH_KEYS)}")
    values: dict[str, float] = {}
    for key, value in table.items():
        if key not in TRUTH_KEYS:
            raise TruthError(f"{where}: unknown key {key!r} (expected one of {', '.join(TRUTH_KEYS)})")
        if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
            raise TruthError(f"{where}.{key} = {value!r}: expected a finite number")
        if value < 0.0 or (key in POSITIVE and value == 0.0):
            raise TruthError(f"{where}.{key} = {value!r}: expected a number {'> 0' if key in POSITIVE else '>= 0'}")
        values[key] = float(value)
    return RobotTruth(**values)


def load_truth(path: str | Path) -> TruthFile:
    """Read a robot truth file; a ``TruthError`` names what is wrong and where."""
    try:
        data = tomllib.loads(Path(path).read_text())
    except OSError as error:
        raise TruthError(f"robot truth file {path}: {error.strerror or error}") from None
    except tomllib.TOMLDecodeError as error:
        raise TruthError(f"robot truth file {path}: not TOML: {error}") from None
    unknown = sorted(set(data) - {"default", "robots"})
    if unknown:
        raise TruthError(f"robot truth file {path}: unknown table {unknown[0]!r} (expected [default] and [robots.K])")
    default = _truth(data.get("default", {}), f"{path}: [default]")
    robots_table = data.get("robots", {})
    if not isinstance(robots_table, dict):
        raise TruthError(f"{path}: robots: expected tables [robots.K], K a robot id")
    robots = {}
    for name, table in robots_table.items():
        if not name.isdigit():
            raise TruthError(f"{path}: [robots.{name}]: expected a robot id (a whole number)")
        robots[int(name)] = _truth(table, f"{path}: [robots.{name}]")
    return TruthFile(default, robots)
