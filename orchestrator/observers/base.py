"""What watches a run: one ``Observer`` protocol, and ``Observers``, the list an engine feeds.

An engine hands what it computes to the list once, and the list hands it to every observer in order
(the trace first, so that whatever a later observer does, the file already holds the point):

* ``point(t, outputs)``: one communication point, every one, undecimated (the engines that step in
  Python: python and monolithic; each observer decimates as it records);
* ``block(rows)``: a float64 array of flat rows ``[t, outputs...]``, already decimated to the trace's
  rate (the native engine fills them in C; the array is reused after the call: copy to keep);
* ``advanced(k)``: ``k`` communication steps are done (after each step, or each call into C);
* ``log(t, level, message)`` and ``link(stream, t, fields)``: a line for the run's log, and a live
  robot link's raw message, from the run or from an observer that relays them (the HIL link reporter);
* ``waiting(what, left)``: before the first point, the start waits for ``what`` (a live robot, on
  which key and endpoint) and gives up in ``left`` seconds (called about each second);
* ``stepping()``: the components are initialized, stepping starts (estimates of the time left count
  from here: building FMUs, waiting for a robot or a viewer is not stepping);
* ``finish()``: the loop is over, however it ended (the trace is finalized by the execution itself:
  its fate decides the run's status).

Observers implement what they need; ``Observer`` gives the rest as no-ops. A new observer (a ROS 2
publisher, a metrics exporter) is one class in one file, added to the list by the execution.
"""

from __future__ import annotations

from typing import Any, Sequence


class Observer:
    """Base of everything that watches a run; every method a no-op until overridden."""

    wants_rows = False  # True: it uses the rows (an engine that fills blocks records none if no observer does)

    def point(self, t: float, outputs: Sequence[Sequence[float]]) -> None:
        """One communication point (engines stepping in Python): every point, undecimated."""

    def block(self, rows: Any) -> None:
        """A block of decimated flat rows ``[t, outputs...]`` (the native engine); reused after the call."""

    def advanced(self, steps_done: int) -> None:
        """``steps_done`` communication steps are done."""

    def log(self, t: float, level: str, message: str) -> None:
        """A line of the run's log."""

    def link(self, stream: str, t: float, fields: dict[str, float]) -> None:
        """A live robot link's raw message (``<vehicle>/<stream>``)."""

    def waiting(self, what: str, left: float) -> None:
        """The start waits for ``what``; it gives up in ``left`` seconds."""

    def stepping(self) -> None:
        """The components are initialized; stepping starts now."""

    def finish(self) -> None:
        """The stepping is over (completed, failed or stopped): release what the observer holds."""

    def delivery(self, step: float, interval: float, call_steps: int | None) -> tuple[float, int | None]:
        """How a block-filling engine should deliver: at most every ``interval`` s of wall time, with
        ``call_steps`` steps per call into C (None: the engine's default); an observer that paces the
        run (the live view) asks for blocks per frame. Returns the two, as this observer wants them."""
        return interval, call_steps


class WaitClock(Observer):
    """How long the start waited for a robot: from the first ``waiting`` to ``stepping`` (0 if it never
    waited), the time a run's "N steps in X s" leaves out with a viewer's wait (``--live-wait``)."""

    def __init__(self, clock: Any = None) -> None:
        import time

        self.clock = clock or time.perf_counter
        self.since: float | None = None
        self.waited = 0.0

    def waiting(self, what: str, left: float) -> None:
        if self.since is None:
            self.since = self.clock()

    def stepping(self) -> None:
        if self.since is not None:
            self.waited, self.since = self.clock() - self.since, None


class Observers(Observer):
    """The observers of one run, in order; an engine calls the list as it would call one observer."""

    def __init__(self, observers: Sequence[Observer] = ()) -> None:
        self.members: list[Observer] = list(observers)

    def add(self, observer: Observer) -> None:
        self.members.append(observer)

    @property
    def wants_rows(self) -> bool:  # type: ignore[override]
        return any(observer.wants_rows for observer in self.members)

    def delivery(self, step: float, interval: float, call_steps: int | None) -> tuple[float, int | None]:
        for observer in self.members:
            interval, call_steps = observer.delivery(step, interval, call_steps)
        return interval, call_steps

    def point(self, t: float, outputs: Sequence[Sequence[float]]) -> None:
        for observer in self.members:
            observer.point(t, outputs)

    def block(self, rows: Any) -> None:
        for observer in self.members:
            observer.block(rows)

    def advanced(self, steps_done: int) -> None:
        for observer in self.members:
            observer.advanced(steps_done)

    def log(self, t: float, level: str, message: str) -> None:
        for observer in self.members:
            observer.log(t, level, message)

    def link(self, stream: str, t: float, fields: dict[str, float]) -> None:
        for observer in self.members:
            observer.link(stream, t, fields)

    def waiting(self, what: str, left: float) -> None:
        for observer in self.members:
            observer.waiting(what, left)

    def stepping(self) -> None:
        for observer in self.members:
            observer.stepping()

    def finish(self) -> None:
        """Every observer's ``finish``, even if one of them raises (the first error is raised after)."""
        failure: BaseException | None = None
        for observer in self.members:
            try:
                observer.finish()
            except BaseException as error:  # noqa: BLE001  (raised below, after the others finished)
                failure = failure or error
        if failure is not None:
            raise failure
