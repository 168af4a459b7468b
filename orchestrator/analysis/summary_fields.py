"""The summary's fields, without numpy: what each vehicle's summary holds, the table's columns and units,
the rows `platoon report --json` prints.

Apart from orchestrator/analysis/metrics.py (which computes the summary, with numpy) so that `platoon report`
can print a summary the run stored in its trace (orchestrator/analysis/stored_summary.py) without importing
numpy: numpy's import alone was about a third of a report (docs/performance.md, "Start-up").
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from orchestrator.analysis.validity import Departure
    from orchestrator.scenario.config import Config

STEADY_FRACTION = 0.1


@dataclass(frozen=True)
class VehicleSummary:
    name: str
    path_offset: float
    gap: float
    speed: float
    path_error_max: float


def first_disturbance(config: Config) -> float | None:
    return min((d.start for d in config.disturbance), default=None)


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
