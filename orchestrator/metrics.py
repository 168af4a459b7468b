"""Errors a platoon user looks at: path error, spacing error, speed error, and their summary.

Definitions (docs/trace-format.md): path error is the signed distance of a vehicle to the path
(circle: r - R, positive outside); gap error is d - d* (d: distance to the vehicle's own target);
speed error is V - V_c. The summary's steady values are means over the last 10 % of the run, and
path_error_max is the largest |path error| after the first disturbance starts (or over the whole run
when there is none).
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np

from .config import Config
from .scenario import path_of
from .trace import Trace

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


def summarize(trace: Trace, config: Config) -> list[VehicleSummary]:
    summaries = []
    start = first_disturbance(config)
    for name in trace.vehicles():
        channel = trace.component(name)
        t = channel["t"]
        steady = t >= t[-1] - STEADY_FRACTION * (t[-1] - t[0])
        errors = path_errors(config, channel["x"], channel["y"])
        window = t >= start if start is not None else np.ones_like(t, dtype=bool)
        summaries.append(
            VehicleSummary(
                name,
                float(np.mean(errors[steady])),
                float(np.mean(channel["gap"][steady])),
                float(np.mean(channel["speed"][steady])),
                float(np.max(np.abs(errors[window]))) if window.any() else float("nan"),
            )
        )
    return summaries


def report_json(summaries: list[VehicleSummary]) -> dict:
    return {"vehicles": [asdict(s) for s in summaries]}
