"""The running summary: the per-vehicle summary of the rows the trace records (same decimation),
accumulated while stepping, so that `platoon run` prints its table without reading the trace again."""

from __future__ import annotations

from typing import Any, Sequence

from orchestrator.analysis.metrics import RunningSummary, VehicleSummary, running_summary
from orchestrator.observers.base import Observer
from orchestrator.scenario.config import Config


class SummaryObserver(Observer):
    """Feeds a ``RunningSummary`` the recorded rows, in blocks."""

    wants_rows = True
    BLOCK = 1024  # rows gathered from single points before the summary takes them

    def __init__(self, config: Config, components: list[tuple[str, list[str]]], steps: int, every: int) -> None:
        step = config.simulation.step
        # the last recorded point is the last multiple of ``every`` steps; rows are every * step apart
        expected_end = (steps // every) * every * step
        self.summary: RunningSummary = running_summary(config, components, 0.0, expected_end, margin=0.5 * every * step)
        self.every = every
        self._count = 0
        self._rows: list[list[float]] = []

    def point(self, t: float, outputs: Sequence[Sequence[float]]) -> None:
        if self._count % self.every == 0:
            row = [t]
            for values in outputs:
                row.extend(values)
            self._rows.append(row)
            if len(self._rows) >= self.BLOCK:
                self._flush()
        self._count += 1

    def block(self, rows: Any) -> None:
        self.summary.add(rows.array())

    def _flush(self) -> None:
        if self._rows:
            self.summary.add(self._rows)
            self._rows = []

    def result(self) -> list[VehicleSummary] | None:
        self._flush()
        return self.summary.result()
