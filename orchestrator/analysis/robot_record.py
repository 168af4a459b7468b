"""What a live run's trace says about each live robot: the wheel commands the run sent and the poses it
received, both stamped on the host's clock (docs/trace-format.md, the live channels), and the model the
run's config gave the robot. ``platoon calibrate`` and ``platoon compare`` read robots through this.

A trace that cannot teach anything about a robot is refused with one line (``RecordError``): no live
vehicle, a run that ended early (recovered, failed, interrupted) unless asked to use it, a robot whose
poses never moved.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from fmus.model.dynamics import M3piDynamics
from orchestrator.analysis.wheel_path import Commands

MOVED = 0.02  # m: a robot whose poses (but 1 %: the noise's tail) lie within this of their median never moved
MIN_POSES = 50


class RecordError(ValueError):
    """A trace that cannot be used (the message names the trace and what is missing)."""


@dataclass(frozen=True)
class RobotRecord:
    """One live robot in one trace. Times are s since ``origin`` (the first command's send time, Unix s)."""

    source: str  # the trace's path
    vehicle: str  # vehicle3
    robot: int
    origin: float
    commands: Commands
    stamp: np.ndarray  # when each pose was taken (the robot side's stamp)
    received: np.ndarray  # when the run received it
    x: np.ndarray
    y: np.ndarray
    heading: np.ndarray  # unwrapped
    model: M3piDynamics  # the m3pi the run's config gave this vehicle

    @property
    def where(self) -> str:
        return f"{self.source}: {self.vehicle} (robot {self.robot})"


def config_model(config: dict[str, Any], vehicle: int) -> M3piDynamics:
    """The m3pi the config gives vehicle ``vehicle``: the model's defaults, then ``[m3pi]``, then
    ``[vehicles.N.m3pi]`` (keys the model does not know are left to the config's own checks)."""
    known = {f.name for f in dataclasses.fields(M3piDynamics)} - {"k_v"}
    table = dict((config or {}).get("m3pi") or {})
    override = ((config or {}).get("vehicles") or {}).get(str(vehicle)) or {}
    table.update(override.get("m3pi") or {})
    k_v = override.get("k_v") or ((config or {}).get("platoon") or {}).get("k_v", 0.5)
    return M3piDynamics(float(k_v), **{k: float(v) for k, v in table.items() if k in known})


def live_vehicles(trace: Any) -> list[str]:
    """The live vehicles of a trace (those with a pose channel), in vehicle order."""
    names = {name.split("/")[0] for name in trace.live if name.endswith("/pose")}
    return sorted(names, key=lambda name: int(name.removeprefix("vehicle")) if name[7:].isdigit() else 0)


def check_complete(trace: Any, source: str) -> None:
    """Refuse a run that ended early: its record stops where it stopped (``--partial`` accepts it)."""
    recovery = trace.metadata.get("platoon.recovery")
    if recovery:
        raise RecordError(f"{source}: a recovered trace (cut short: the run did not finish writing it); "
                          "pass --partial to use what it holds")
    status = (trace.run or {}).get("status", "")
    if status != "completed":
        raise RecordError(f"{source}: the run ended early ({status or 'no end status'}); pass --partial to use "
                          "what it holds")


def robot_records(trace: Any, source: str | Path) -> list[RobotRecord]:
    """Every live robot of ``trace`` (read with ``orchestrator.trace.load``); ``RecordError`` if none."""
    source = str(source)
    vehicles = live_vehicles(trace)
    if not vehicles:
        raise RecordError(f"{source}: no live vehicle (no /platoon/vehicleK/pose channel): calibrate and compare "
                          "need the trace of a run with a live robot (docs/hil.md)")
    return [_record(trace, source, vehicle) for vehicle in vehicles]


def applied_between(seq: np.ndarray, stamp: np.ndarray, echoed: np.ndarray) -> tuple[np.ndarray | None, np.ndarray | None]:
    """When the robot applied each command (numbers ``seq``), as its poses (taken at ``stamp``, echoing the number
    of the last command applied) bound it: after the last pose before the first echo of it (or of a later
    one), by that echo. (None, None) when the poses echo nothing (a motion capture of its own)."""
    if not np.any(echoed > 0):
        return None, None
    highest = np.maximum.accumulate(echoed)
    first = np.searchsorted(highest, seq, side="left")
    latest = np.where(first < len(stamp), stamp[np.minimum(first, len(stamp) - 1)], np.inf)
    earliest = np.where(first > 0, stamp[np.maximum(first - 1, 0)], -np.inf)
    return earliest, latest


def _record(trace: Any, source: str, vehicle: str) -> RobotRecord:
    pose, command = trace.live.get(f"{vehicle}/pose", {}), trace.live.get(f"{vehicle}/command", {})
    link = trace.live.get(f"{vehicle}/link", {})
    number = int(vehicle.removeprefix("vehicle"))
    robot = int(link["robot"][-1]) if len(link.get("robot", ())) else number
    where = f"{source}: {vehicle} (robot {robot})"
    sent = np.asarray(command.get("sent", ()), dtype=float)
    if len(sent) < 2:
        raise RecordError(f"{where}: the run sent it {len(sent)} wheel command(s): nothing to identify")
    stamp = np.asarray(pose.get("stamp", ()), dtype=float)
    if len(stamp) < MIN_POSES:
        raise RecordError(f"{where}: {len(stamp)} pose(s) recorded, at least {MIN_POSES} needed")
    x, y = np.asarray(pose["x"], dtype=float), np.asarray(pose["y"], dtype=float)
    reach = float(np.percentile(np.hypot(x - np.median(x), y - np.median(y)), 99.0))
    if reach < MOVED:
        raise RecordError(f"{where}: its poses never moved (99 % within {reach * 1e3:.1f} mm of their median): "
                          "nothing to identify")
    order = np.argsort(stamp, kind="stable")
    origin = float(sent[0])
    earliest, latest = applied_between(np.asarray(command["seq"], dtype=float), stamp[order],
                                       np.asarray(pose["command_seq"], dtype=float)[order])
    commands = Commands(sent - origin, np.asarray(command["deadline"], dtype=float) - origin,
                        np.asarray(command["left"], dtype=float), np.asarray(command["right"], dtype=float),
                        None if earliest is None else earliest - origin, None if latest is None else latest - origin)
    return RobotRecord(source, vehicle, robot, origin, commands, stamp[order] - origin,
                       np.asarray(pose["received"], dtype=float)[order] - origin, x[order], y[order],
                       np.unwrap(np.asarray(pose["heading"], dtype=float)[order]),
                       config_model(trace.config, number))
