"""A run's watch on its own validity: each vehicle's first collision, pass or impossible speed, as the rows
are recorded (orchestrator/analysis/validity.py), logged to the run's log (the trace's /platoon/log, the
live view) at the time it happened, and kept for the run's result (`platoon run`'s summary, a sweep's row).

It sees the rows the trace records (the same decimation), so every engine finds the same departures, and
`platoon report` finds them again in the trace. Python-stepped points are gathered into blocks before
numpy sees them (a point at a time would cost more than the check).

A short run does not import numpy for the watch: while numpy is not loaded, a block whose rows are plainly
inside the model (``ValidityWatch.plainly_inside``, plain Python) is passed without it, in a run that records
up to ``PLAIN_BUDGET`` vehicle-rows; a block near a limit, and every block of a longer run, go to numpy,
whose verdicts these are either way. numpy was a fifth of a 10-step run's start-up (docs/performance.md,
"Start-up")."""

from __future__ import annotations

import sys
from typing import TYPE_CHECKING, Any, Callable, Sequence

from orchestrator.observers.base import Observer
from orchestrator.scenario.raw_config import recorded_rows, step_count
from orchestrator.support.rows import RowBlock

if TYPE_CHECKING:
    from orchestrator.scenario.config import Config
    from orchestrator.analysis.validity import Departure, ValidityWatch

Log = Callable[[float, str, str], None]
GATHERED = 256  # Python-stepped rows checked at a time
# in a paced run (a live robot's): a block of GATHERED took 3-5 ms of one 10 ms step; ten rows are a fraction
# of a millisecond, and the watch is built before the first step, not inside one
PACED_GATHERED = 10
# vehicle-rows a run checks in plain Python (1.5-2 µs each) before numpy (~0.05 s to import) takes over
PLAIN_BUDGET = 10_000


def numpy_loaded() -> bool:
    """Whether this process has imported numpy already (then it checks every block)."""
    return "numpy" in sys.modules


class ValidityObserver(Observer):
    """Checks the recorded rows of ``components`` (name, output names) against ``config``'s limits."""

    wants_rows = True

    def __init__(self, config: Config, components: Sequence[tuple[str, Sequence[str]]], log: Log,
                 paced: bool = False) -> None:
        self._settings = (config, list(components))
        self.gathered = PACED_GATHERED if paced else GATHERED
        self.every = config.simulation.trace_every
        self.to_log = log  # not `log`: that is the hook every observer is called on
        self._watch: "ValidityWatch | None" = None
        self._count = 0
        self._rows: list[list[float]] = []
        rows = recorded_rows(step_count(config.simulation.stop_time, config.simulation.step), self.every)
        # a run that records more than the budget will need numpy: from its first block, not after the budget
        self._plain_left = PLAIN_BUDGET if rows * config.platoon.count <= PLAIN_BUDGET else 0
        if paced:  # what a block near a limit needs is loaded before the first step, not inside one (5 ms)
            import numpy  # noqa: F401

            self._the_watch()

    def point(self, t: float, outputs: Sequence[Sequence[float]]) -> None:
        if self._count % self.every == 0:
            row = [t]
            for values in outputs:
                row.extend(values)
            self._rows.append(row)
            if len(self._rows) >= self.gathered:
                self._flush()
        self._count += 1

    def block(self, rows: Any) -> None:
        block = RowBlock.coerce(rows)
        if len(block) and not self._plainly_inside(block, len(block)):
            self._check(block.array())

    def _flush(self) -> None:
        if self._rows:
            rows, self._rows = self._rows, []
            if not self._plainly_inside(rows, len(rows)):
                import numpy as np

                self._check(np.array(rows, dtype=float))

    def _plainly_inside(self, rows: "RowBlock | list[list[float]]", count: int) -> bool:
        """True when the watch saw, without numpy, that ``rows`` come near no limit (module docstring)."""
        watch = self._the_watch()
        cost = count * max(1, len(watch.names))
        if numpy_loaded() or cost > self._plain_left:
            return False  # numpy is there (it folds a block faster), or the run is long enough to pay for it
        self._plain_left -= cost
        return watch.plainly_inside(rows.tolist() if isinstance(rows, RowBlock) else rows)

    def _the_watch(self) -> "ValidityWatch":
        if self._watch is None:
            from orchestrator.analysis.validity import watch_for

            self._watch = watch_for(*self._settings)
        return self._watch

    def _check(self, rows: Any) -> None:
        for departure in self._the_watch().add(rows):
            self.to_log(departure.t, "Warning", f"left the model: {departure.text()}")

    def finish(self) -> None:
        self._flush()

    def result(self) -> "list[Departure]":
        self._flush()
        return self._watch.result() if self._watch is not None else []
