"""The paper's Fig. 2 as data: which output of which component feeds which input of which other.

Lateral information flows backward (the target's, then each vehicle's pose, speed and rates into the
vehicle behind); velocity information flows forward (each vehicle's speed, gap and rates into the
component ahead, vehicle 1's into the target). Every signal travels with the sender's ``output_time``
(into the receiver's ``*.time`` input). A vehicle whose speed law reads the on-board sensor (acc, cacc)
also gets the pose and motion of the component ahead on its ``sensor.*`` inputs, wired directly: a
sensor measures, it does not communicate, so these never pass through a link.
The master, the SSP export and the libcosim tests all read this one list.

A link (docs/links.md) on one direction between two adjacent components is a component of its own, a
Link FMU: the sender's message goes into the link's ``in.*`` inputs, and the link's outputs (the
message in use, same names as the sender's) into the receiver's inputs where the sender's went.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Iterable

from orchestrator.trace.format import link_name  # noqa: F401  (a Link's component name, re-exported here)

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


LINK_FMU = "Link"
BACKWARD, FORWARD = "backward", "forward"


def link_input(output: str) -> str:
    """The Link input that carries a sender's ``output`` (its output_time into in.time)."""
    return "in.time" if output == OUTPUT_TIME else f"in.{output}"


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


def component_names(count: int, linked: frozenset[tuple[str, int]] = frozenset()) -> list[str]:
    """Front to back: the target, then vehicles 1..count (the Gauss-Seidel order). A link in
    ``linked`` ((direction, vehicle) pairs) steps right after its sender: vehicle N's backward link
    just before vehicle N, its forward link just after it, so under Gauss-Seidel a message reaches
    its receiver as soon as it would without the link."""
    names = [TARGET]
    for i in range(1, count + 1):
        names += [link_name(BACKWARD, i)] if (BACKWARD, i) in linked else []
        names.append(vehicle_name(i))
        names += [link_name(FORWARD, i)] if (FORWARD, i) in linked else []
    return names


def _through(source: str, destination: str, signals: tuple[tuple[str, str], ...], link: str | None) -> list[Connection]:
    """One direction's message from ``source`` to ``destination``, straight or through ``link``."""
    if link is None:
        return [Connection(source, out, destination, inp) for out, inp in signals]
    return ([Connection(source, out, link, link_input(out)) for out, _ in signals]
            + [Connection(link, out, destination, inp) for out, inp in signals])


def platoon_connections(count: int, linked: frozenset[tuple[str, int]] = frozenset(),
                        sensing: Iterable[int] = ()) -> list[Connection]:
    """Fig. 2's connections; the messages of the (direction, vehicle) pairs in ``linked`` pass
    through their Link components (``link_name``); then the sensor connections of the vehicles
    numbered in ``sensing`` (direct: a sensor never passes through a link)."""
    names = [TARGET] + [vehicle_name(i) for i in range(1, count + 1)]
    connections = []
    for vehicle, (ahead, behind) in enumerate(zip(names, names[1:]), start=1):
        backward = link_name(BACKWARD, vehicle) if (BACKWARD, vehicle) in linked else None
        forward = link_name(FORWARD, vehicle) if (FORWARD, vehicle) in linked else None
        connections += _through(ahead, behind, LATERAL_SIGNALS, backward)
        signals = LEAD_SIGNALS if ahead == TARGET else FOLLOWER_SIGNALS
        connections += _through(behind, ahead, signals, forward)
    for index in sensing:
        ahead, behind = names[index - 1], names[index]
        connections += [Connection(ahead, out, behind, inp) for out, inp in SENSOR_SIGNALS]
    return connections
