"""The one interface the master loop knows: ``Component``, and what a live endpoint adds to it.

An FMU (``orchestrator.components.FmuComponent``) and a live robot on Zenoh
(``bridge.live.LiveVehicle``) both implement ``Component``, so the master steps either without
noticing which it holds. This module imports nothing heavy (no FMPy), so the bridge can depend on it
alone.

A live endpoint also implements ``LiveComponent``: it runs in wall-clock time (the master paces itself
when any component says ``realtime``), and it hands the run what it saw on its link (state changes
for the log, raw messages and link statistics for the trace) without knowing how the trace is written.
"""

from __future__ import annotations

import math
import statistics
from dataclasses import dataclass
from typing import Any, Callable, Protocol, Sequence, runtime_checkable

from fmus.errors import ComponentError

__all__ = ["Component", "ComponentError", "LiveComponent", "LiveEvent", "LiveRecord", "percentile_summary"]


class Component(Protocol):
    """Named inputs and outputs that can advance in time, in the order of an FMI co-simulation slave:
    ``initialize``, any number of ``set_inputs``/``get_outputs``, ``end_initialization``, then per step
    ``set_inputs``, ``step(t, h)``, ``get_outputs``, and ``close`` at the end, whatever happened. A
    failure raises ``ComponentError`` naming the component, the time and the reason."""

    name: str
    inputs: list[str]
    outputs: list[str]
    input_defaults: list[float]

    def initialize(self, start_time: float) -> None: ...
    def set_inputs(self, values: Sequence[float]) -> None: ...
    def get_outputs(self) -> list[float]: ...
    def end_initialization(self) -> None: ...
    def step(self, time: float, step: float) -> None: ...
    def close(self) -> None: ...


@dataclass(frozen=True)
class LiveEvent:
    """A line for the run's log: ``level`` is "Info", "Warning" or "Error"."""

    level: str
    message: str


@dataclass(frozen=True)
class LiveRecord:
    """One raw message of a live link, for the trace: ``stream`` names it (e.g. "pose", "command"),
    ``fields`` are numbers (wall-clock receive or send time included)."""

    stream: str
    fields: dict[str, float]


@runtime_checkable
class LiveComponent(Protocol):
    """What a component that talks to real hardware adds to ``Component``."""

    realtime: bool  # True: the run paces itself to wall-clock time while this component is in it
    # set by the run before initialize: called with what the start waits for (robot, key, endpoint) and
    # the seconds left before it gives up, each second while it waits (the terminal is the run's, not ours)
    on_wait: Callable[[str, float], None] | None

    def drain_events(self) -> list[LiveEvent]:
        """Log lines since the last call (state changes, dropped messages), oldest first."""
        ...

    def drain_records(self) -> list[LiveRecord]:
        """Raw messages sent and received since the last call, oldest first."""
        ...

    def link_statistics(self) -> dict[str, Any]:
        """Counters of the link so far (messages received, accepted, dropped by reason, ...)."""
        ...


def percentile_summary(name: str, samples: Sequence[float], empty: float | None = None) -> dict[str, float]:
    """``name.median``, ``name.p99``, ``name.max`` and ``name.count`` of ``samples``: the one way live
    statistics (round trips, pose ages, step jitter) are summed up. Without samples: nothing, or every
    key with the value ``empty`` (and count 0), for a record whose fields must not change."""
    if not samples:
        if empty is None:
            return {}
        return {f"{name}.median": empty, f"{name}.p99": empty, f"{name}.max": empty, f"{name}.count": 0}
    ordered = sorted(samples)
    p99 = ordered[min(len(ordered) - 1, math.ceil(0.99 * len(ordered)) - 1)]
    return {f"{name}.median": statistics.median(ordered), f"{name}.p99": p99, f"{name}.max": ordered[-1],
            f"{name}.count": len(ordered)}
