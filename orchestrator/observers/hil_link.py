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
LINK_STREAM = "link"  # the stream of a live component's link statistics: /platoon/<component>/link


def link_numbers(statistics: dict[str, Any]) -> dict[str, float]:
    """The numbers of a link's statistics (its robot, state and claim are text: the summary has them)."""
    return {k: float(v) for k, v in statistics.items() if isinstance(v, (int, float))}


def live_streams(names: Sequence[str]) -> dict[str, list[str]]:
    """Every raw stream the live components ``names`` will record (``<component>/pose``, ``/command``,
    ``/link``) and its numbers, in order, before any link opens: the live view advertises them before its
    first viewer connects (a channel advertised mid-run is one a connected viewer may fail to subscribe to)."""
    if not names:
        return {}
    from bridge.live import RECORD_FIELDS, initial_link_statistics  # Zenoh is imported only by live runs

    link = list(link_numbers(initial_link_statistics()))
    streams: dict[str, list[str]] = {}
    for name in sorted(names):
        streams.update({f"{name}/{stream}": list(fields) for stream, fields in RECORD_FIELDS.items()})
        streams[f"{name}/{LINK_STREAM}"] = link
    return streams


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
                outlet.link(f"{component.name}/{LINK_STREAM}", t, link_numbers(component.link_statistics()))

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
