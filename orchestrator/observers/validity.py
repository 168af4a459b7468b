"""A run's watch on its own validity: each vehicle's first collision, pass or impossible speed, as the rows
are recorded (orchestrator/analysis/validity.py), logged to the run's log (the trace's /platoon/log, the
live view) at the time it happened, and kept for the run's result (`platoon run`'s summary, a sweep's row).

It sees the rows the trace records (the same decimation), so every engine finds the same departures, and
`platoon report` finds them again in the trace. Python-stepped points are gathered into blocks before
numpy sees them (a point at a time would cost more than the check)."""

from __future__ import annotations

from typing import TYPE_CHECKING, Any, Callable, Sequence

from orchestrator.observers.base import Observer
from orchestrator.scenario.config import Config
from orchestrator.support.rows import RowBlock

if TYPE_CHECKING:
    from orchestrator.analysis.validity import Departure, ValidityWatch

Log = Callable[[float, str, str], None]
GATHERED = 256  # Python-stepped rows checked at a time


class ValidityObserver(Observer):
    """Checks the recorded rows of ``components`` (name, output names) against ``config``'s limits."""

    wants_rows = True

    def __init__(self, config: Config, components: Sequence[tuple[str, Sequence[str]]], log: Log) -> None:
        self._settings = (config, list(components))
        self.every = config.simulation.trace_every
        self.to_log = log  # not `log`: that is the hook every observer is called on
        self._watch: "ValidityWatch | None" = None
        self._count = 0
        self._rows: list[list[float]] = []

    def point(self, t: float, outputs: Sequence[Sequence[float]]) -> None:
        if self._count % self.every == 0:
            row = [t]
            for values in outputs:
                row.extend(values)
            self._rows.append(row)
            if len(self._rows) >= GATHERED:
                self._flush()
        self._count += 1

    def block(self, rows: Any) -> None:
        block = RowBlock.coerce(rows)
        if len(block):
            self._check(block.array())

    def _flush(self) -> None:
        if self._rows:
            import numpy as np

            rows, self._rows = self._rows, []
            self._check(np.array(rows, dtype=float))

    def _check(self, rows: Any) -> None:
        if self._watch is None:
            from orchestrator.analysis.validity import watch_for

            self._watch = watch_for(*self._settings)
        for departure in self._watch.add(rows):
            self.to_log(departure.t, "Warning", f"left the model: {departure.text()}")

    def finish(self) -> None:
        self._flush()

    def result(self) -> "list[Departure]":
        self._flush()
        return self._watch.result() if self._watch is not None else []
