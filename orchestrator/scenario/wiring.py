"""The paper's Fig. 2 as data: which output of which component feeds which input of which other.

Lateral information flows backward (the target's, then each vehicle's pose, speed and rates into the
vehicle behind); velocity information flows forward (each vehicle's speed, gap and rates into the
component ahead, vehicle 1's into the target). Every signal travels with the sender's ``output_time``
(into the receiver's ``*.time`` input). A vehicle whose speed law reads the on-board sensor (acc, cacc)
also gets the pose and motion of the component ahead on its ``sensor.*`` inputs, wired directly: a
sensor measures, it does not communicate, so these never pass through a link.
The master, the SSP export and the libcosim tests all read this one list.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Iterable

TARGET = "target"

# Every FMU's output naming the time its other outputs describe; it feeds the receiver's <side>.time.
OUTPUT_TIME = "output_time"

# (sender output, receiver input) pairs for each direction of flow.
LATERAL_SIGNALS = tuple(
    (name, f"target.{name}") for name in ("x", "y", "heading", "speed", "speed_rate", "turn_rate")
) + ((OUTPUT_TIME, "target.time"),)
FOLLOWER_SIGNALS = tuple(
    (name, f"follower.{name}") for name in ("speed", "gap", "speed_rate", "gap_rate")
) + ((OUTPUT_TIME, "follower.time"),)
# The on-board sensor's signals: the component ahead's pose and motion (sender output, receiver input).
SENSOR_SIGNALS = tuple(
    (name, f"sensor.{name}") for name in ("x", "y", "heading", "speed", "speed_rate", "turn_rate")
) + ((OUTPUT_TIME, "sensor.time"),)
LEAD_SIGNALS = tuple((name, f"lead.{name}") for name in ("speed", "gap", "speed_rate", "gap_rate")) + (
    (OUTPUT_TIME, "lead.time"),
)


@dataclass(frozen=True)
class Connection:
    source: str
    output: str
    destination: str
    input: str

    def __str__(self) -> str:
        return f"{self.source}.{self.output} -> {self.destination}.{self.input}"


def vehicle_name(index: int) -> str:
    """Component name of vehicle ``index`` (1-based), also its trace channel /platoon/<name>."""
    return f"vehicle{index}"


def component_names(count: int) -> list[str]:
    """Front to back: the target, then vehicles 1..count (the Gauss-Seidel order)."""
    return [TARGET] + [vehicle_name(i) for i in range(1, count + 1)]


def platoon_connections(count: int, sensing: Iterable[int] = ()) -> list[Connection]:
    """Fig. 2's connections, then the sensor connections of the vehicles numbered in ``sensing``."""
    names = component_names(count)
    connections = []
    for ahead, behind in zip(names, names[1:]):
        connections += [Connection(ahead, out, behind, inp) for out, inp in LATERAL_SIGNALS]
        signals = LEAD_SIGNALS if ahead == TARGET else FOLLOWER_SIGNALS
        connections += [Connection(behind, out, ahead, inp) for out, inp in signals]
    for index in sensing:
        ahead, behind = names[index - 1], names[index]
        connections += [Connection(ahead, out, behind, inp) for out, inp in SENSOR_SIGNALS]
    return connections
