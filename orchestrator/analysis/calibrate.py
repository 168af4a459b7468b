"""Identify a live robot's physics from the traces of live runs, by output error (``platoon calibrate``).

Drive the model (``orchestrator.analysis.wheel_path``: ``M3piDynamics``' dead-band, gains, limit, motor lag
and unicycle) with the wheel commands the run recorded, shifted by the command latency, and fit its path
to the poses the run received at the times they were taken. The fit is scipy's ``least_squares`` over
the wheel gains, motor time constant, wheel speed limit, track and command latency. The dead-band is
not smooth in the path (a command is in it or not), so it is found on its own profile (the path's
misfit against the dead-band, the rest held), between two least-squares fits.

The path is compared piece by piece (segments of a few seconds), each piece moved rigidly onto the
recorded one first (a closed-form rotation and translation): the pieces need no start pose of their
own, and a slightly wrong gain cannot send a two-minute path astray and the fit with it. The first
second after the first command is left out: the wheels' state there (at rest, or the emulator's
flying start) is forgotten after a few motor time constants.

The pose latency (a pose older than its stamp) cannot be told from the command latency: the path only shows
when a command moved the robot as the stamps see it, so the fitted command latency is the loop's whole delay
(what the model's sampled loop needs: it moves the observed robot command_latency + pose_latency after a
command). The pose latency is written as the nominal 0, not identified; how long poses took from their stamp
to the run (the delivery, which the run dead-reckons over) is measured and printed.

Each parameter gets a 95 % confidence interval (from the fit's Jacobian and residual variance; the
dead-band's from its profile) and is "identified" only when the trace excited it: a wheel limit the
wheels never reached, a dead-band no command came near, or an interval wider than ``TOLERANCE`` is
"not identified" and written as the model's nominal value, never as the fit's guess.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, fields, replace
from typing import Callable, Sequence

import numpy as np
from scipy.optimize import least_squares, minimize_scalar

from fmus.model.dynamics import M3piDynamics
from orchestrator.analysis.robot_record import RobotRecord
from orchestrator.analysis.wheel_path import DeadReckoned, dead_reckon, rigid_fit, segments, wheel_history

SETTLE = 1.0  # s after the first command before the poses count
SEGMENTS = (1.0, 4.0)  # s: pieces compared rigidly, short first (robust from a far start), then longer (precise)
# poses a second compared in the first fit and in the others: the final fits take every pose of a 200 Hz motion
# capture (the time constant's error from the poses' noise: about 0.9 % rms at every third pose, 0.5 % at all)
COARSE_RATE, FINE_RATE = 50.0, 200.0
Z95 = 1.959964  # two-sided 95 % normal quantile
CHI2_95 = 3.841459  # 95 % quantile of chi-squared with one degree of freedom (the profile's interval)
DEADBAND_SPAN = 0.1  # m/s: the dead-band is looked for in [0, this]
REACHED = 0.3  # s: a wheel limit counts as reached when a wheel was held at it this long
NEAR_ZERO = 0.3  # s: a dead-band counts as excited when commands this long lay inside it (or near 0 for none)

# (name, unit, lower bound, upper bound, scale): the least-squares parameters
FITTED = (
    ("wheel_gain_right", "", 0.2, 5.0, 0.1),
    ("wheel_gain_left", "", 0.2, 5.0, 0.1),
    ("motor_time_constant", "s", 0.002, 2.0, 0.02),
    ("wheel_speed_max", "m/s", 0.05, 10.0, 0.1),
    ("track", "m", 0.01, 1.0, 0.005),
    ("command_latency", "s", 0.0, 0.5, 0.01),
)
DYNAMICS = ("track", "wheel_speed_max", "motor_time_constant", "wheel_gain_right", "wheel_gain_left", "wheel_deadband")
# how wide (half the 95 % interval) an estimate may be and still count as identified
TOLERANCE = {"wheel_gain_right": ("rel", 0.05), "wheel_gain_left": ("rel", 0.05), "motor_time_constant": ("rel", 0.1),
             "wheel_speed_max": ("rel", 0.05), "track": ("rel", 0.05), "command_latency": ("abs", 0.005),
             "wheel_deadband": ("abs", 0.003), "pose_latency": ("abs", 0.005)}
UNITS = {name: unit for name, unit, *_ in FITTED} | {"wheel_deadband": "m/s", "pose_latency": "s"}
ORDER = ("wheel_gain_right", "wheel_gain_left", "motor_time_constant", "wheel_speed_max", "wheel_deadband", "track",
         "command_latency", "pose_latency")


@dataclass(frozen=True)
class Estimate:
    """One parameter: the value written, the 95 % interval, and whether the trace identified it."""

    name: str
    value: float
    low: float
    high: float
    identified: bool
    note: str = ""  # why not identified, or how it was measured

    @property
    def unit(self) -> str:
        return UNITS[self.name]


@dataclass(frozen=True)
class RobotCalibration:
    robot: int
    sources: tuple[str, ...]  # "trace: vehicleK" of each record used
    estimates: dict[str, Estimate]
    residual: float  # m, rms per axis of the calibrated path against the poses
    residual_before: float  # m, the same for the run's own model
    pose_noise: float  # m, the poses' own noise per axis (from their second differences)
    delivery: float  # s, median of received - stamp
    poses: int
    seconds: float  # of recorded motion used

    def values(self) -> dict[str, float]:
        return {name: estimate.value for name, estimate in self.estimates.items()}


def nominal_values(model: M3piDynamics) -> dict[str, float]:
    """The model's own values of every calibrated parameter (latencies: none)."""
    nominal = {f.name: f.default for f in fields(M3piDynamics) if f.name in DYNAMICS}
    return {**nominal, "command_latency": 0.0, "pose_latency": 0.0}


def model_values(model: M3piDynamics) -> dict[str, float]:
    """What a run's config said of its robot: its m3pi's values, no latency."""
    return {**{n: getattr(model, n) for n in DYNAMICS}, "command_latency": 0.0}


def robot_model(model: M3piDynamics, values: dict[str, float]) -> M3piDynamics:
    return replace(model, **{name: values[name] for name in DYNAMICS if name in values})


class PathProblem:
    """The recorded poses of one robot (one or more records) and the model's path against them."""

    def __init__(self, records: Sequence[RobotRecord], segment: float, tick: Callable[[], None] = lambda: None,
                 rate: float = math.inf) -> None:
        """``rate``: at most this many poses a second are compared (a coarse first fit needs few)."""
        self.records, self.tick = list(records), tick
        self.windows = [_thinned(record.stamp, rate) & (record.stamp >= SETTLE) for record in self.records]
        self.labels = [segments(record.stamp[w], segment) for record, w in zip(self.records, self.windows)]
        self.latency_range = echoed_range(self.records)

    def path(self, record: RobotRecord, window: np.ndarray, values: dict[str, float]) -> DeadReckoned:
        return dead_reckon(robot_model(record.model, values), record.commands, values["command_latency"],
                           record.stamp[window])

    def residuals(self, values: dict[str, float]) -> np.ndarray:
        """Model minus recorded position (x then y, every pose in the window), each piece moved onto the record."""
        self.tick()
        parts = []
        for record, window, labels in zip(self.records, self.windows, self.labels):
            path = self.path(record, window, values)
            x, y = record.x[window], record.y[window]
            mx, my, _ = rigid_fit(path.x, path.y, x, y, labels)
            parts += [mx - x, my - y]
        return np.concatenate(parts)

    def cost(self, values: dict[str, float]) -> float:
        r = self.residuals(values)
        return float(r @ r)


def _thinned(stamps: np.ndarray, rate: float) -> np.ndarray:
    """Every k-th pose, k the smallest that keeps at most ``rate`` poses a second."""
    keep = np.zeros(len(stamps), dtype=bool)
    interval = float(np.median(np.diff(stamps))) if len(stamps) > 1 else 1.0
    # (a hair's tolerance: poses 4.99999 ms apart are 200 a second, not to be thinned to every second one)
    keep[::max(int(math.ceil(1.0 / (rate * interval) - 1e-3)) if math.isfinite(rate) else 1, 1)] = True
    return keep


def top_speed(records: Sequence[RobotRecord]) -> float:
    """The fastest the recorded poses moved (m/s, over quarter seconds: the poses' noise averaged out)."""
    fastest = 0.0
    for r in records:
        later = np.searchsorted(r.stamp, r.stamp + 0.25)
        ok = later < len(r.stamp)
        span = r.stamp[later[ok]] - r.stamp[ok]
        moved = np.hypot(r.x[later[ok]] - r.x[ok], r.y[later[ok]] - r.y[ok])
        fastest = max(fastest, float(np.max(moved / np.maximum(span, 1e-9), initial=0.0)))
    return fastest


def echoed_latency(records: Sequence[RobotRecord]) -> float:
    """Where the command latency starts: the middle of the window the poses' echoes put each command's application
    in (median over the commands), else 20 ms. With echoes the path hardly depends on a latency outside those
    windows (every command is held to its window), so the fit must start inside them."""
    middles = [0.5 * (r.commands.earliest + r.commands.latest) - r.commands.sent for r in records
               if r.commands.earliest is not None and r.commands.latest is not None]
    middle = np.concatenate(middles) if middles else np.array([])
    middle = middle[np.isfinite(middle)]
    return float(np.clip(np.median(middle), 0.0, 0.5)) if len(middle) else 0.02


def echoed_range(records: Sequence[RobotRecord]) -> tuple[float, float] | None:
    """The command latencies the poses' echoes allow for the typical command: from the median of how long after
    its sending each command's window opens to the median of how long after it closes (None without echoes).

    Every command is held to its window, so outside this range the path no longer depends on the latency: a
    latency below it applies nearly every command at its window's opening, which a slightly slower motor
    lag mimics, and the fit can settle there with a flat gradient (measured: a loop delay of 28.9 ms found as
    24.0 ms, the time constant 3 % long). Inside it, the path depends on the latency as without echoes."""
    opens = [r.commands.earliest - r.commands.sent for r in records if r.commands.earliest is not None]
    closes = [r.commands.latest - r.commands.sent for r in records if r.commands.latest is not None]
    if not opens or not closes:
        return None
    low, high = (np.concatenate(parts) for parts in (opens, closes))
    low, high = low[np.isfinite(low)], high[np.isfinite(high)]
    if not len(low) or not len(high):
        return None
    lowest, highest = float(np.median(low)), float(np.median(high))
    return (max(lowest, 0.0), highest) if highest > max(lowest, 0.0) else None


def least_squares_fit(problem: PathProblem, values: dict[str, float], free: Sequence[str]) -> tuple[dict[str, float], object]:
    """Fit the ``free`` parameters (the rest held at ``values``); returns the values and scipy's result. With
    echoes the command latency stays within what they allow (``echoed_range``)."""
    spec = {name: (low, high, scale) for name, _, low, high, scale in FITTED}
    if problem.latency_range is not None:
        spec["command_latency"] = (*problem.latency_range, spec["command_latency"][2])
    start = np.array([min(max(values[n], spec[n][0]), spec[n][1]) for n in free])

    def residuals(p: np.ndarray) -> np.ndarray:
        return problem.residuals({**values, **dict(zip(free, p.tolist()))})

    result = least_squares(residuals, start, bounds=([spec[n][0] for n in free], [spec[n][1] for n in free]),
                           x_scale=np.array([spec[n][2] for n in free]), method="trf", xtol=1e-10, ftol=1e-10,
                           max_nfev=60)
    return {**values, **dict(zip(free, result.x.tolist()))}, result




def pose_noise(records: Sequence[RobotRecord]) -> float:
    """The poses' noise per axis from their second differences (white noise: variance 6 sigma^2; the motion's
    own share at 200 poses a second is micrometres)."""
    second = np.concatenate([np.diff(a, 2) for r in records for a in (r.x, r.y)])
    return float(np.sqrt(np.mean(second ** 2) / 6.0))


def _within(name: str, value: float, half: float) -> bool:
    kind, limit = TOLERANCE[name]
    return half <= (limit * abs(value) if kind == "rel" else limit)


def _limit_reached(problem: PathProblem, values: dict[str, float]) -> tuple[float, float]:
    """(seconds a wheel's target was at the limit, the fastest target below it) over the records."""
    held, fastest = 0.0, 0.0
    for record in problem.records:
        model = robot_model(record.model, {**values, "wheel_speed_max": math.inf})
        history = wheel_history(model, record.commands, values["command_latency"])
        span = np.append(np.diff(history.times), 0.0)
        wanted = np.maximum(np.abs(history.target_right), np.abs(history.target_left))
        held += float(span[wanted >= values["wheel_speed_max"]].sum())
        fastest = max(fastest, float(wanted.max()))
    return held, fastest


def _deadband_excited(problem: PathProblem, deadband: float) -> float:
    """Seconds a wheel's command lay inside the dead-band (not zero), or within 10 mm/s of zero for none."""
    edge = max(deadband, 0.01)
    total = 0.0
    for record in problem.records:
        c = record.commands
        span = np.append(np.diff(c.sent), 0.0)
        for wheel in (c.left, c.right):
            total += float(span[(np.abs(wheel) > 0.0) & (np.abs(wheel) < edge)].sum())
    return total


def deadband_best(problem: PathProblem, values: dict[str, float]) -> float:
    """The dead-band that fits best, the rest held: a grid over [0, DEADBAND_SPAN], then Brent around its best."""
    grid = np.linspace(0.0, DEADBAND_SPAN, 11)
    costs = [problem.cost({**values, "wheel_deadband": float(d)}) for d in grid]
    k = int(np.argmin(costs))
    found = minimize_scalar(lambda d: problem.cost({**values, "wheel_deadband": float(d)}),
                            bounds=(grid[max(k - 1, 0)], grid[min(k + 1, len(grid) - 1)]), method="bounded",
                            options={"xatol": 2e-4})
    return float(found.x) if found.fun < costs[k] else float(grid[k])


def deadband_interval(problem: PathProblem, values: dict[str, float], variance: float) -> tuple[float, float, float]:
    """(best, low, high): the dead-band's profile near its estimate and where the misfit stays within the 95 %
    likelihood-ratio bound (chi-squared, one degree of freedom) of its least."""
    best = values["wheel_deadband"]
    grid = np.unique(np.append(np.linspace(max(best - 0.006, 0.0), best + 0.006, 13), best))
    costs = np.array([problem.cost({**values, "wheel_deadband": float(d)}) for d in grid])
    k = int(np.argmin(costs))
    inside = np.flatnonzero(costs - costs[k] <= CHI2_95 * variance)
    # the interval reaches to the first grid point outside on each side: the profile between two is not known
    return float(grid[k]), float(grid[max(inside.min() - 1, 0)]), float(grid[min(inside.max() + 1, len(grid) - 1)])


def delivery(records: Sequence[RobotRecord]) -> float:
    """How long the poses took from their stamp to the run (median): the run dead-reckons over it."""
    return float(np.median(np.concatenate([r.received - r.stamp for r in records])))


def pose_latency(nominal: float) -> Estimate:
    """A pose older than its stamp: inside the fitted command latency, never apart from it."""
    return Estimate("pose_latency", nominal, -math.inf, math.inf, False,
                    "inside command_latency, the loop's whole delay")


def _fit(problem: PathProblem, values: dict[str, float], free: list[str]) -> tuple[dict[str, float], dict[str, float], float]:
    """The dead-band (if free) on its profile, the rest held, then least squares over the rest of ``free``.
    Returns (values, 95 % half-widths of the least-squares parameters, residual variance)."""
    if "wheel_deadband" in free:
        values["wheel_deadband"] = deadband_best(problem, values)
    fitted = [n for n in free if n != "wheel_deadband"]
    values, result = least_squares_fit(problem, values, fitted)
    jacobian = result.jac
    variance = 2.0 * result.cost / max(len(result.fun) - len(fitted) - 1, 1)
    covariance = variance * np.linalg.pinv(jacobian.T @ jacobian)
    half = {n: Z95 * math.sqrt(max(covariance[i, i], 0.0)) for i, n in enumerate(fitted)}
    return values, half, variance


def calibrate_robot(records: Sequence[RobotRecord], tick: Callable[[], None] = lambda: None) -> RobotCalibration:
    """Identify one robot from its records (module docstring); what the traces did not excite is the nominal."""
    model = records[0].model
    nominal = nominal_values(model)
    start = model_values(model)
    # the limit starts where the robot was seen to go: a limit above every wheel's target would give the fit
    # nothing to pull on, were the robot's own one below them
    first = {**start, "command_latency": echoed_latency(records), "wheel_speed_max": top_speed(records)}
    free = [n for n, *_ in FITTED]
    values, _ = least_squares_fit(PathProblem(records, SEGMENTS[0], tick, rate=COARSE_RATE), first, free)
    problem = PathProblem(records, SEGMENTS[1], tick, rate=FINE_RATE)
    notes: dict[str, str] = {}
    held, fastest = _limit_reached(problem, values)
    if held < REACHED:
        free.remove("wheel_speed_max")
        values["wheel_speed_max"] = max(nominal["wheel_speed_max"], fastest)
        notes["wheel_speed_max"] = f"never reached (the wheels were asked at most {fastest:.3f} m/s)"
    values, half, variance = _fit(problem, {**values, "wheel_deadband": 0.0}, free + ["wheel_deadband"])
    best, low, high = deadband_interval(problem, values, variance)
    values["wheel_deadband"] = best
    if _deadband_excited(problem, best) < NEAR_ZERO:
        notes["wheel_deadband"] = "no command came near zero"
    estimates: dict[str, Estimate] = {}
    for name in free:
        h = half[name]
        good = _within(name, values[name], h) and name not in notes
        estimates[name] = Estimate(name, values[name], values[name] - h, values[name] + h, good,
                                   notes.get(name, "" if good else f"interval wider than {_tolerance(name)}"))
    d_good = "wheel_deadband" not in notes and _within("wheel_deadband", best, 0.5 * (high - low))
    estimates["wheel_deadband"] = Estimate("wheel_deadband", best, low, high, d_good, notes.get(
        "wheel_deadband", "" if d_good else f"interval wider than {_tolerance('wheel_deadband')}"))
    if "wheel_speed_max" in notes:
        v = values["wheel_speed_max"]
        estimates["wheel_speed_max"] = Estimate("wheel_speed_max", v, v, math.inf, False, notes["wheel_speed_max"])
    unidentified = [n for n, e in estimates.items() if not e.identified and n != "wheel_speed_max"]
    if unidentified:  # what the trace did not teach is the model's, and the rest is fitted around it
        values.update({n: nominal[n] for n in unidentified})
        values, half, variance = _fit(problem, values, [n for n in free if n not in unidentified])
        for name, e in list(estimates.items()):
            if name == "wheel_deadband" and name in unidentified:  # its interval around the nominal, the rest refitted
                _, low, high = deadband_interval(problem, values, variance)
                estimates[name] = replace(e, value=nominal[name], low=low, high=high)
            elif name in unidentified:
                estimates[name] = replace(e, value=nominal[name])
            elif name in half:
                estimates[name] = replace(e, value=values[name], low=values[name] - half[name],
                                          high=values[name] + half[name])
    estimates["pose_latency"] = pose_latency(nominal["pose_latency"])
    before = start
    return RobotCalibration(
        records[0].robot, tuple(f"{r.source}: {r.vehicle}" for r in records),
        {name: estimates[name] for name in ORDER}, _rms(problem.residuals(values)), _rms(problem.residuals(before)),
        pose_noise(records), delivery(records), int(sum(w.sum() for w in problem.windows)),
        float(sum(r.stamp[w][-1] - r.stamp[w][0] for r, w in zip(records, problem.windows))))


def _rms(residuals: np.ndarray) -> float:
    return float(np.sqrt(np.mean(residuals ** 2)))


def _tolerance(name: str) -> str:
    kind, limit = TOLERANCE[name]
    if kind == "rel":
        return f"+-{limit:.0%}"
    return f"+-{limit * 1e3:g} {'ms' if UNITS[name] == 's' else 'mm/s'}"
