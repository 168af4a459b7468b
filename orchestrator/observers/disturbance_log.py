"""Lines of the run's log (the trace's /platoon/log, the live view's log) when each disturbance starts and
ends, stamped with its own start and end times: a user scrolling a run's log in Foxglove sees when it was
struck and what struck it, next to the link and run lines."""

from __future__ import annotations

from typing import TYPE_CHECKING, Any, Callable, Sequence

from orchestrator.observers.base import Observer
from orchestrator.support.rows import RowBlock

if TYPE_CHECKING:
    from orchestrator.scenario.config import Config

Log = Callable[[float, str, str], None]


class DisturbanceLog(Observer):
    """Logs ``config``'s disturbances through ``log`` once the run records a row at or after their start and
    end: the rows the trace records (the same decimation), so every engine logs the same lines, and a run
    that stopped before a row past one (a failure, Ctrl-C) logs nothing of it."""

    wants_rows = True

    def __init__(self, config: Config, log: Log) -> None:
        step = config.simulation.step
        self.every, self.slack = config.simulation.trace_every, 1e-9 * step  # a row's time is k h, rounded
        self.to_log = log  # not `log`: that is the hook every observer is called on
        self._count = 0
        events = []
        for pulse in config.disturbance:
            events.append((pulse.start, f"disturbance starts: {pulse.text()}"))
            events.append((pulse.start + pulse.duration, f"disturbance ends: {pulse.what()}"))
        self.events = sorted(events, key=lambda event: event[0])

    def point(self, t: float, outputs: Sequence[Sequence[float]]) -> None:
        if self._count % self.every == 0:
            self._reached(t)
        self._count += 1

    def block(self, rows: Any) -> None:
        block = RowBlock.coerce(rows)
        if len(block):
            self._reached(block.time(-1))

    def _reached(self, t: float) -> None:
        while self.events and self.events[0][0] <= t + self.slack:
            at, message = self.events.pop(0)
            self.to_log(at, "Info", message)
