"""Lines of the run's log (the trace's /platoon/log, the live view's log) when each disturbance starts and
ends, stamped with its own start and end times: a user scrolling a run's log in Foxglove sees when it was
struck and what struck it, next to the link and run lines."""

from __future__ import annotations

from typing import Callable

from orchestrator.observers.base import Observer
from orchestrator.scenario.config import Config

Log = Callable[[float, str, str], None]


class DisturbanceLog(Observer):
    """Logs ``config``'s disturbances through ``log`` as the run reaches their start and end (once the step
    that crosses them is done; a run stopped before one logs nothing of it)."""

    def __init__(self, config: Config, log: Log) -> None:
        self.step, self.to_log = config.simulation.step, log  # not `log`: that is the hook every observer is called on
        events = []
        for pulse in config.disturbance:
            events.append((pulse.start, f"disturbance starts: {pulse.text()}"))
            events.append((pulse.start + pulse.duration, f"disturbance ends: {pulse.what()}"))
        self.events = sorted(events, key=lambda event: event[0])

    def advanced(self, steps_done: int) -> None:
        reached = steps_done * self.step * (1.0 + 1e-12)  # t_k = k h, to the rounding of the product
        while self.events and self.events[0][0] <= reached:
            at, message = self.events.pop(0)
            self.to_log(at, "Info", message)
