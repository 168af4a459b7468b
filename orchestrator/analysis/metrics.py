"""Errors a platoon user looks at: path error, spacing error, speed error, and their summary.

Definitions (docs/trace-format.md): path error is the signed distance of a vehicle to the path
(circle: r - R, positive outside); gap error is d - d* (d: distance to the vehicle's own target);
speed error is V - V_c. The summary's steady values are means over the last 10 % of the run, and
path_error_max is the largest |path error| after the first disturbance starts (or over the whole run
when there is none).
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Sequence

import numpy as np

from orchestrator.analysis.summary_fields import (  # noqa: F401  (re-exported: the summary's fields, without numpy)
    STEADY_FRACTION, SUMMARY_COLUMNS, SUMMARY_UNITS, SummaryColumn, VehicleSummary, first_disturbance,
    path_error_interval, report_json, summary_rows)
from orchestrator.scenario.scenario import path_of
from orchestrator.trace.format import vehicle_names

if TYPE_CHECKING:  # a run accumulates its summary without the trace reader (mcap's reader: start-up time)
    from orchestrator.scenario.config import Config
    from orchestrator.trace import Trace


def path_errors(config: Config, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Signed distance of each (x, y) to the configured path, m."""
    distance = np.frompyfunc(path_of(config).signed_distance, 2, 1)
    return np.asarray(distance(x, y), dtype=float)


SUMMARY_OUTPUTS = ("x", "y", "gap", "speed")  # what a vehicle's summary reads
SUMMARY_BLOCK = 4096  # rows folded at a time when summarizing a loaded trace
SUM_GROUP = 1024  # the steady window's rows summed at a time (``RunningSummary``)


def _group_sum(blocks: list[np.ndarray]) -> np.ndarray:
    """The sum of one group's rows (rows x vehicles x 3), one contiguous array: the same additions for the
    same rows, however they were split."""
    return np.ascontiguousarray(np.concatenate(blocks) if len(blocks) > 1 else blocks[0]).sum(axis=0)


class RunningSummary:
    """The per-vehicle summary, accumulated from rows as they are recorded (one pass, bounded memory).

    ``platoon run`` feeds it every recorded row, so printing the table does not re-read the trace;
    ``summarize`` feeds it a trace's rows: one implementation of the summary either way. Rows are flat,
    ``[t, outputs of every component...]``, in blocks.

    The steady window is the last ``STEADY_FRACTION`` of the recorded time span, whose end is only
    known at the last row. The caller predicts it (``expected_end``); rows clearly inside or outside the
    predicted window are folded into sums at once, and the few rows within ``margin`` of its start are
    kept until ``result`` knows the real end. If the real end lies too far from the prediction (a run
    that stopped early), ``result`` returns None and the caller reads the trace instead.
    """

    def __init__(self, config: Config, columns: dict[str, dict[str, int]], start: float,
                 expected_end: float, margin: float) -> None:
        self.names = vehicle_names(list(columns))
        self._columns = np.array([[columns[n][o] for o in SUMMARY_OUTPUTS] for n in self.names], dtype=np.intp)
        self._distance = np.frompyfunc(path_of(config).signed_distance, 2, 1)
        self._disturbed_from = first_disturbance(config)
        self._start = start
        self._margin = margin
        self._predicted = expected_end - STEADY_FRACTION * (expected_end - start)
        count = len(self.names)
        # the steady window's rows are summed in groups of SUM_GROUP by their index among the recorded rows, and
        # the groups' sums in the groups' order: the same additions whichever blocks the rows came in (the run's,
        # or a trace's read back), so `platoon run` and `platoon report` agree to the last bit
        self._rows_seen = 0
        self._group_sums: dict[int, np.ndarray] = {}  # complete groups: group -> sum (path error, gap, speed)
        self._open: dict[int, list[np.ndarray]] = {}  # groups not summed yet: group -> blocks of their rows' values
        self._first_group: int | None = None  # the first inside row's group: summed at the end, with the boundary's
        self._steady_rows = 0
        self._boundary: list[tuple[int, float, np.ndarray]] = []  # rows near the predicted window start: (index, t, values)
        self._error_max = np.full(count, -np.inf)
        # gap and speed are summed as deviations from d* and V_c: a mean of values near 25 m/s would
        # carry rounding noise (~1e-12 over 10^3 rows) larger than the deviations the table shows
        self._reference = np.array([0.0, config.platoon.d_star, config.platoon.speed])
        self.last_time: float | None = None

    def add(self, rows: np.ndarray) -> None:
        """Fold a block of flat rows into the summary."""
        rows = np.asarray(rows, dtype=float)
        if rows.ndim != 2 or not len(rows):
            return
        t = rows[:, 0]
        picked = rows[:, self._columns]  # rows x vehicles x (x, y, gap, speed)
        errors = self._distance(picked[:, :, 0], picked[:, :, 1]).astype(float)
        window = t >= self._disturbed_from if self._disturbed_from is not None else np.ones(len(t), dtype=bool)
        if window.any():
            self._error_max = np.maximum(self._error_max, np.max(np.abs(errors[window]), axis=0))
        values = np.stack([errors, picked[:, :, 2], picked[:, :, 3]], axis=2) - self._reference  # rows x vehicles x 3
        inside = t > self._predicted + self._margin
        near = ~inside & (t >= self._predicted - self._margin)
        first = self._rows_seen
        self._rows_seen += len(t)
        for index in np.flatnonzero(near):
            self._boundary.append((first + int(index), float(t[index]), values[index]))
        rows_inside = np.flatnonzero(inside)
        if len(rows_inside):
            self._steady_rows += len(rows_inside)
            groups = (first + rows_inside) // SUM_GROUP
            if self._first_group is None:
                self._first_group = int(groups[0])
            cuts = np.flatnonzero(np.diff(groups)) + 1
            for part in np.split(np.arange(len(rows_inside)), cuts):
                self._open.setdefault(int(groups[part[0]]), []).append(values[rows_inside[part]])
            for group in [g for g in self._open if g < groups[-1] and g != self._first_group]:  # complete
                self._group_sums[group] = _group_sum(self._open.pop(group))
        self.last_time = float(t[-1])

    def result(self) -> list[VehicleSummary] | None:
        """The summaries, or None when the recorded span ended too far from the predicted end."""
        if self.last_time is None:
            return None
        threshold = self.last_time - STEADY_FRACTION * (self.last_time - self._start)
        if abs(threshold - self._predicted) >= self._margin:
            return None
        sums, count = dict(self._group_sums), self._steady_rows
        rest = {group: list(blocks) for group, blocks in self._open.items()}
        for index, t, values in reversed(self._boundary):  # before every inside row of their group: in index order
            if t >= threshold:
                rest.setdefault(index // SUM_GROUP, []).insert(0, values[np.newaxis])
                count += 1
        sums.update({group: _group_sum(blocks) for group, blocks in rest.items()})
        total = np.zeros((len(self.names), 3))
        for group in sorted(sums):
            total += sums[group]
        means = total / count + self._reference
        error_max = np.where(np.isfinite(self._error_max), self._error_max, np.nan)
        return [VehicleSummary(name, float(means[i, 0]), float(means[i, 1]), float(means[i, 2]), float(error_max[i]))
                for i, name in enumerate(self.names)]


def running_summary(config: Config, components: Sequence[tuple[str, Sequence[str]]], start: float,
                    expected_end: float, margin: float) -> RunningSummary:
    """A ``RunningSummary`` for flat rows of ``components`` (name, output names) in this order."""
    columns: dict[str, dict[str, int]] = {}
    offset = 1  # column 0 is t
    for name, outputs in components:
        columns[name] = {output: offset + i for i, output in enumerate(outputs)}
        offset += len(outputs)
    vehicles = {n: columns[n] for n in vehicle_names(list(columns))}
    return RunningSummary(config, vehicles, start, expected_end, margin)


def summarize(trace: Trace, config: Config) -> list[VehicleSummary]:
    """The summary of a trace's recorded rows (the same computation ``platoon run`` does as it records)."""
    names = vehicle_names(list(trace.channels))
    if not names:
        return []
    t = trace.component(names[0])["t"]
    if not len(t):
        return []
    components = [(n, SUMMARY_OUTPUTS) for n in names]
    end = float(t[-1])
    # the end is known exactly here: a margin of rounding size keeps only rows at the window's start aside
    summary = running_summary(config, components, float(t[0]), end, margin=1e-9 * (abs(end) + 1.0))
    for first in range(0, len(t), SUMMARY_BLOCK):
        block = slice(first, first + SUMMARY_BLOCK)
        summary.add(np.column_stack([t[block]] + [trace.component(n)[o][block] for n in names for o in SUMMARY_OUTPUTS]))
    result = summary.result()
    assert result is not None  # the predicted end is the real one
    return result
