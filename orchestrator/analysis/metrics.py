"""Errors a platoon user looks at: path error, spacing error, speed error, and their summary.

Definitions (docs/trace-format.md): path error is the signed distance of a vehicle to the path
(circle: r - R, positive outside); gap error is d - d* (d: distance to the vehicle's own target);
speed error is V - V_c. The summary's steady values are means over the last 10 % of the run, and
path_error_max is the largest |path error| after the first disturbance starts (or over the whole run
when there is none).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, Sequence

import numpy as np

from orchestrator.scenario.scenario import path_of
from orchestrator.trace.format import vehicle_names

if TYPE_CHECKING:  # a run accumulates its summary without the trace reader (mcap's reader: start-up time)
    from orchestrator.analysis.validity import Departure
    from orchestrator.scenario.config import Config
    from orchestrator.trace import Trace

STEADY_FRACTION = 0.1


@dataclass(frozen=True)
class VehicleSummary:
    name: str
    path_offset: float
    gap: float
    speed: float
    path_error_max: float


def path_errors(config: Config, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Signed distance of each (x, y) to the configured path, m."""
    distance = np.frompyfunc(path_of(config).signed_distance, 2, 1)
    return np.asarray(distance(x, y), dtype=float)


def first_disturbance(config: Config) -> float | None:
    return min((d.start for d in config.disturbance), default=None)


SUMMARY_OUTPUTS = ("x", "y", "gap", "speed")  # what a vehicle's summary reads
SUMMARY_BLOCK = 4096  # rows folded at a time when summarizing a loaded trace


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
        self._steady_sums = np.zeros((count, 3))  # path error, gap, speed
        self._steady_rows = 0
        self._boundary: list[tuple[float, np.ndarray]] = []  # rows near the predicted window start: (t, values)
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
        if inside.any():
            self._steady_sums += values[inside].sum(axis=0)
            self._steady_rows += int(inside.sum())
        for index in np.flatnonzero(near):
            self._boundary.append((float(t[index]), values[index]))
        self.last_time = float(t[-1])

    def result(self) -> list[VehicleSummary] | None:
        """The summaries, or None when the recorded span ended too far from the predicted end."""
        if self.last_time is None:
            return None
        threshold = self.last_time - STEADY_FRACTION * (self.last_time - self._start)
        if abs(threshold - self._predicted) >= self._margin:
            return None
        sums, count = self._steady_sums.copy(), self._steady_rows
        for t, values in self._boundary:
            if t >= threshold:
                sums += values
                count += 1
        means = sums / count + self._reference
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


@dataclass(frozen=True)
class SummaryColumn:
    """One quantity of the summary table: its JSON key, its table header and its unit."""

    key: str
    label: str
    unit: str


# What the summary table shows, in its order; `platoon report --json` reports each under its key (with
# the absolute gap and speed besides), so the table and the JSON cannot tell different stories.
SUMMARY_COLUMNS = (
    SummaryColumn("path_offset", "path offset", "m"),
    SummaryColumn("gap_error", "gap - d*", "m"),
    SummaryColumn("speed_error", "speed - V_c", "m/s"),
    SummaryColumn("path_error_max", "max |path error|", "m"),
)
SUMMARY_UNITS = {"path_offset": "m", "gap": "m", "gap_error": "m", "speed": "m/s", "speed_error": "m/s",
                 "path_error_max": "m"}


def path_error_interval(config: Config) -> tuple[float | None, str]:
    """Where path_error_max is taken: (start s, or None for the whole run) and how the table says it."""
    start = first_disturbance(config)
    return start, ("whole run" if start is None else f"t >= {start:g} s")


def summary_rows(summaries: list[VehicleSummary], config: Config) -> list[dict[str, float | str]]:
    """Per vehicle: the summary's values and the deviations the table shows (gap - d*, speed - V_c)."""
    return [{"name": s.name, "path_offset": s.path_offset, "gap": s.gap, "gap_error": s.gap - config.platoon.d_star,
             "speed": s.speed, "speed_error": s.speed - config.platoon.speed, "path_error_max": s.path_error_max}
            for s in summaries]


def report_json(summaries: list[VehicleSummary], config: Config, departures: "list[Departure]") -> dict:
    """The summary as ``platoon report --json`` prints it: the table's quantities, their units and intervals,
    and where the run left the model (``validity``: orchestrator/analysis/validity.py)."""
    from orchestrator.analysis.validity import departures_json

    start, interval = path_error_interval(config)
    return {
        "units": SUMMARY_UNITS,
        "steady_window": {"last_fraction": STEADY_FRACTION,
                          "quantities": ["path_offset", "gap", "gap_error", "speed", "speed_error"],
                          "text": f"means over the last {STEADY_FRACTION:.0%} of the recorded time"},
        "path_error_max_interval": {"from_s": start, "text": interval},
        "vehicles": summary_rows(summaries, config),
        "validity": departures_json(departures, config),
    }
