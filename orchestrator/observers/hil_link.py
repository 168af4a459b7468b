"""What the live robots' links saw, into the run's record: after each communication point, the live
components' state changes (as log lines), raw poses and commands, and every second their link
statistics go to the other observers (the trace, the live view); at the end, the summary of the links
and of the pacing, as ``platoon.hil`` metadata and for the table `platoon run` prints."""

from __future__ import annotations

import json
from typing import Any, Callable, Sequence

from fmus.component import Component, LiveComponent
from fmus.realtime import Pacer
from orchestrator.observers.base import Observer

LINK_STATS_INTERVAL = 1.0  # s of simulated (= wall) time between two link statistics messages


class LinkReporter(Observer):
    """Relays the live components' events and raw messages to ``outlet`` after each point."""

    def __init__(self, components: Sequence[Component], outlet: Observer, pacer: Pacer,
                 metadata: Callable[[str, dict[str, str]], None]) -> None:
        self.live = [c for c in components if isinstance(c, LiveComponent)]
        self.outlet, self.pacer, self.metadata = outlet, pacer, metadata
        self._next_stats = 0.0
        self.summary: dict[str, dict[str, Any]] = {}

    def point(self, t: float, outputs: Sequence[Sequence[float]]) -> None:
        self._relay(t)

    def _relay(self, t: float, final: bool = False) -> None:
        outlet = self.outlet
        for component in self.live:
            for event in component.drain_events():
                outlet.log(t, event.level, event.message)
            for record in component.drain_records():
                outlet.link(f"{component.name}/{record.stream}", t, record.fields)
        if t >= self._next_stats or final:
            self._next_stats = t + LINK_STATS_INTERVAL
            for component in self.live:
                numbers = {k: float(v) for k, v in component.link_statistics().items() if isinstance(v, (int, float))}
                outlet.link(f"{component.name}/link", t, numbers)

    def close_links(self, t: float) -> dict[str, dict[str, Any]]:
        """Drain what is left, record the links' final statistics (the last ``/link`` message always
        holds the final counts, however close to the previous one the run ended) and the summary as
        ``platoon.hil`` metadata, and return it. ``t``: the last communication point the run reached."""
        self._relay(t, final=True)
        summary = {"pacing": self.pacer.summary()}
        summary.update({c.name: c.link_statistics() for c in self.live})
        self.metadata("platoon.hil", {name: json.dumps(values) for name, values in summary.items()})
        self.summary = summary
        return summary
