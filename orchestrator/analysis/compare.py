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


SPEED_WINDOW = 0.2  # s: speeds compared are the distance covered over this window (both runs alike)


@dataclass(frozen=True)
class VehicleDifference:
    """How far one vehicle of one run is from the same vehicle of another, over their common time points."""

    name: str
    points: int
    path_rms: float  # m, distance between the two positions
    path_max: float
    path_max_at: float  # s
    speed_rms: float  # m/s, difference of the speeds over the ground (SPEED_WINDOW)
    speed_max: float


def ground_speed(t: np.ndarray, x: np.ndarray, y: np.ndarray, window: float = SPEED_WINDOW) -> np.ndarray:
    """Speed over the ground from positions: the distance covered over ``window`` s centred on each point (a live
    vehicle's speed output is its controller's estimate; what the robot did is in its poses)."""
    half = window / 2.0
    ahead = np.clip(np.searchsorted(t, t + half), 0, len(t) - 1)
    behind = np.clip(np.searchsorted(t, t - half), 0, len(t) - 1)
    span = np.maximum(t[ahead] - t[behind], 1e-12)
    return np.hypot(x[ahead] - x[behind], y[ahead] - y[behind]) / span


def run_differences(run: Trace, other: Trace) -> list[VehicleDifference]:
    """Each vehicle both traces hold, compared at the time points both recorded (a run cut short: its part)."""
    differences = []
    for name in [v for v in run.vehicles() if v in other.vehicles()]:
        a, b = run.component(name), other.component(name)
        ka, kb = np.round(a["t"] * 1e6).astype(np.int64), np.round(b["t"] * 1e6).astype(np.int64)
        common, ia, ib = np.intersect1d(ka, kb, return_indices=True)
        if len(common) < 2:
            continue
        t = a["t"][ia]
        distance = np.hypot(a["x"][ia] - b["x"][ib], a["y"][ia] - b["y"][ib])
        speed = ground_speed(t, a["x"][ia], a["y"][ia]) - ground_speed(t, b["x"][ib], b["y"][ib])
        k = int(np.argmax(distance))
        differences.append(VehicleDifference(name, len(common), float(np.sqrt(np.mean(distance ** 2))),
                                             float(distance[k]), float(t[k]), float(np.sqrt(np.mean(speed ** 2))),
                                             float(np.max(np.abs(speed)))))
    return differences
