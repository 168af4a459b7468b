"""How far one run is from another: the co-simulation against the monolithic reference."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from orchestrator.trace import Trace


@dataclass(frozen=True)
class Deviation:
    position: float  # largest distance between the same vehicle in the two runs, m
    position_where: str  # "vehicleN at t = ... s"
    gap: float  # largest |gap difference|, m
    speed: float  # largest |speed difference|, m/s


def deviations(run: Trace, reference: Trace, since: float = 0.0) -> Deviation:
    """Largest position, gap and speed differences over every vehicle and common time point >= since."""
    worst_position, where, worst_gap, worst_speed = 0.0, "", 0.0, 0.0
    for name in reference.vehicles():
        a, b = run.component(name), reference.component(name)
        if a["t"].shape != b["t"].shape or not np.allclose(a["t"], b["t"], rtol=0.0, atol=1e-9):
            raise ValueError(f"{name}: the two traces were not recorded at the same times")
        window = a["t"] >= since
        distance = np.hypot(a["x"] - b["x"], a["y"] - b["y"])[window]
        k = int(np.argmax(distance))
        if distance[k] >= worst_position:
            worst_position, where = float(distance[k]), f"{name} at t = {a['t'][window][k]:.2f} s"
        worst_gap = max(worst_gap, float(np.max(np.abs(a["gap"] - b["gap"])[window])))
        worst_speed = max(worst_speed, float(np.max(np.abs(a["speed"] - b["speed"])[window])))
    return Deviation(worst_position, where, worst_gap, worst_speed)
