"""Where a run leaves the model: vehicles that collide, pass the one ahead, or reach speeds no vehicle reaches.

The co-simulation integrates the documented semantics wherever they lead. Under the paper's law with held,
lossy links a vehicle's speed is V d*/d of a gap its links show stale, and a string of them can amplify
that noise until one vehicle runs at thousands of m/s while another crawls, or two meet (the law's 1/d
singularity): true of the equations, impossible for any vehicle, and outside what the linear analysis
(docs/model.md, section 12) describes. A run says so, from the rows it records:

- **collision**: the true distance to the component ahead (the target for vehicle 1), from the recorded
  positions, at or below ``validity.min_gap`` (default: a vehicle's size, 4.5 m for a kinematic vehicle, a
  car's length, 0.095 m for an m3pi, its diameter; never more than half the smallest equilibrium gap, so
  that a small-scale platoon at its equilibrium is inside);
- **reversal**: the vehicle is ahead of the component it follows, along the path's direction of travel at
  that component (a pass between two records shows as this without a collision);
- **speed**: |speed| above ``validity.max_speed`` (default 3 V_c, times the initial speed factor when the
  platoon starts faster; none for an m3pi, whose wheels bound it).

The first departure of each kind per vehicle is kept. ``ValidityWatch`` folds flat rows ``[t, outputs...]``
(the run's observer feeds it while stepping, ``departures_of_trace`` a trace's rows): one implementation for
`platoon run`, `platoon report`, a sweep's row and the string-stability commands. Pure computation, no I/O.

numpy is imported where the rows are folded, not with this module: a quiet run whose rows stay plainly inside
(``ValidityWatch.plainly_inside``, plain Python) never needs it, and importing it was a fifth of a short
run's start-up (docs/performance.md, "Start-up").
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass
from typing import TYPE_CHECKING, Iterable, Sequence

from orchestrator.scenario.wiring import TARGET
from orchestrator.trace.format import vehicle_names

if TYPE_CHECKING:
    from orchestrator.scenario.config import Config
    import numpy as np

    from orchestrator.trace import Trace

VEHICLE_LENGTH = 4.5  # m: a car's length, the kinematic vehicle's size
M3PI_SIZE = 0.095  # m: the m3pi's diameter
SPEED_FACTOR = 3.0  # the default speed limit over V_c
WATCHED = ("x", "y", "speed")
KINDS = ("collision", "reversal", "speed")
LEFT_MODEL = "run.left_model"  # a sweep row's column: ``departures_cell``, "" inside the model
# ``plainly_inside``'s margins: relative, far above the few ulps by which its sums and math.hypot may differ
# from numpy's (~1e-15), and absolute, above the rounding of subnormal products
MARGIN = 1e-9
TINY = 1e-300


@dataclass(frozen=True)
class Limits:
    """The run's limits: the minimum gap (m), and each vehicle's largest speed (m/s, inf: none)."""

    min_gap: float
    max_speed: tuple[float, ...]


def _equilibrium_gap(config: Config, vehicle: int) -> float:
    p = config.platoon
    return p.d_star if config.speed_law_of(vehicle) == "paper" else p.resolved_standstill_gap + p.time_gap * p.speed


def limits_of(config: Config) -> Limits:
    """``config``'s limits, its ``[validity]`` table's where given, else the defaults (module docstring)."""
    count, stated = config.platoon.count, config.validity
    kinds = [config.override(i).dynamics or config.platoon.dynamics for i in range(1, count + 1)]
    if stated.min_gap is not None:
        min_gap = stated.min_gap
    else:
        size = max(M3PI_SIZE if kind == "m3pi" else VEHICLE_LENGTH for kind in kinds)
        min_gap = min(size, 0.5 * min(_equilibrium_gap(config, i) for i in range(1, count + 1)))
    default = SPEED_FACTOR * config.platoon.speed * max(1.0, config.initial.speed_factor)
    speeds = tuple(stated.max_speed if stated.max_speed is not None else math.inf if kind == "m3pi" else default
                   for kind in kinds)
    return Limits(min_gap, speeds)


@dataclass(frozen=True)
class Departure:
    """A vehicle leaving the model: ``kind`` (``KINDS``) first seen at ``t``; ``value`` the gap (m; along the
    path for a reversal) or the speed (m/s), ``limit`` what it crossed, ``ahead`` the component it follows."""

    kind: str
    vehicle: str
    t: float
    value: float
    limit: float
    ahead: str = ""

    def text(self) -> str:
        if self.kind == "collision":
            return (f"{self.vehicle} collided with {self.ahead} at t = {self.t:g} s (gap {self.value:.3g} m, at or "
                    f"below the minimum {self.limit:g} m)")
        if self.kind == "reversal":
            return f"{self.vehicle} passed {self.ahead} at t = {self.t:g} s (gap along the path {self.value:.3g} m)"
        return f"{self.vehicle} reached {self.value:.4g} m/s at t = {self.t:g} s (beyond {self.limit:g} m/s)"


def _tangent(config: Config, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The path's direction of travel at (x, y): the line's heading, or the circle's tangent there."""
    import numpy as np

    path = config.path
    if path.kind == "line":
        return np.full_like(x, math.cos(path.heading)), np.full_like(x, math.sin(path.heading))
    sign = 1.0 if path.direction == "ccw" else -1.0
    dx, dy = x - path.center[0], y - path.center[1]
    radius = np.hypot(dx, dy)
    radius = np.where(radius > 0.0, radius, 1.0)
    return -sign * dy / radius, sign * dx / radius


class ValidityWatch:
    """Folds flat rows (``columns``: component -> output -> column) and keeps each vehicle's first departure
    of each kind; ``add`` returns the ones a block adds, in time order."""

    def __init__(self, config: Config, columns: dict[str, dict[str, int]]) -> None:
        self.config, self.limits = config, limits_of(config)
        self.names = vehicle_names(list(columns))
        self._aheads = [TARGET] + self.names[:-1]
        self._pairs = [(ahead, name) for ahead, name in zip(self._aheads, self.names) if ahead in columns]
        self._columns = columns
        # per pair: the columns of the ahead's x and y, the follower's x and y
        sides = ((0, "x"), (0, "y"), (1, "x"), (1, "y"))
        self._pair_columns = [tuple(columns[pair[side]][axis] for side, axis in sides) for pair in self._pairs]
        self.departures: dict[tuple[str, str], Departure] = {}

    def plainly_inside(self, rows: Iterable[Sequence[float]]) -> bool:
        """True when no row comes near a limit, seen in plain Python: ``add`` would find nothing in them. False
        when a row is at a limit, near one (within ``MARGIN``) or not finite: then ``add`` decides. The margins
        cover the few ulps by which these sums and math.hypot may differ from numpy's, so the verdicts are
        ``add``'s either way; a run that never comes near a limit needs no numpy (module docstring)."""
        speeds = [(self._columns[name]["speed"], limit) for name, limit in zip(self.names, self.limits.max_speed)]
        near_gap = (self.limits.min_gap * (1.0 + MARGIN)) ** 2
        path = self.config.path
        circle = path.kind != "line"
        sign, (center_x, center_y) = (1.0 if path.direction == "ccw" else -1.0), path.center
        tx, ty = math.cos(path.heading), math.sin(path.heading)  # a line's direction (a circle's: per row)
        for row in rows:
            if not all(abs(row[column]) <= limit for column, limit in speeds):  # add's test, exactly
                return False
            for ax, ay, bx, by in self._pair_columns:
                x, y = row[ax], row[ay]
                dx, dy = x - row[bx], y - row[by]
                if not dx * dx + dy * dy > near_gap:  # its gap is above the minimum with the margin (or overflows)
                    return False
                if circle:  # _tangent's, at the vehicle ahead
                    radius = math.hypot(x - center_x, y - center_y)
                    if not radius > TINY:
                        return False
                    tx, ty = -sign * (y - center_y) / radius, sign * (x - center_x) / radius
                along_x, along_y = dx * tx, dy * ty
                if not along_x + along_y > MARGIN * (abs(along_x) + abs(along_y)) + TINY:  # plainly still behind
                    return False
        return True

    def add(self, rows: np.ndarray) -> list[Departure]:
        import numpy as np

        rows = np.asarray(rows, dtype=float)
        if rows.ndim != 2 or not len(rows) or not self.names:
            return []
        t, found, column = rows[:, 0], [], self._columns
        speeds = rows[:, [column[name]["speed"] for name in self.names]]
        speed_limit = np.array(self.limits.max_speed[:len(self.names)])
        fast = np.abs(speeds) > speed_limit
        for vehicle in np.flatnonzero(fast.any(axis=0)):  # its first row only: a runaway exceeds it for thousands
            first = int(np.argmax(fast[:, vehicle]))
            found.append(Departure("speed", self.names[vehicle], float(t[first]), float(speeds[first, vehicle]),
                                   float(speed_limit[vehicle])))
        if self._pairs:  # every pair at once (rows x pairs): a platoon of thousands is one numpy pass a block
            ax, ay, bx, by = (rows[:, np.array(columns, dtype=np.intp)] for columns in zip(*self._pair_columns))
            dx, dy = ax - bx, ay - by
            tx, ty = _tangent(self.config, ax, ay)
            along, gap = dx * tx + dy * ty, np.hypot(dx, dy)
            for kind, hits, values in (("collision", gap <= self.limits.min_gap, gap), ("reversal", along < 0.0, along)):
                for pair in np.flatnonzero(hits.any(axis=0)):
                    first = int(np.argmax(hits[:, pair]))
                    ahead, name = self._pairs[pair]
                    found.append(Departure(kind, name, float(t[first]), float(values[first, pair]),
                                           self.limits.min_gap if kind == "collision" else 0.0, ahead))
        new = []
        for departure in sorted(found, key=lambda d: (d.t, KINDS.index(d.kind))):
            key = (departure.kind, departure.vehicle)
            if key not in self.departures:
                self.departures[key] = departure
                new.append(departure)
        return new

    def result(self) -> list[Departure]:
        return sorted(self.departures.values(), key=lambda d: (d.t, KINDS.index(d.kind), d.vehicle))


def watch_for(config: Config, components: Sequence[tuple[str, Sequence[str]]]) -> ValidityWatch:
    """A ``ValidityWatch`` for flat rows of ``components`` (name, output names) in this order."""
    columns: dict[str, dict[str, int]] = {}
    offset = 1  # column 0 is t
    for name, outputs in components:
        columns[name] = {output: offset + i for i, output in enumerate(outputs)}
        offset += len(outputs)
    return ValidityWatch(config, columns)


def departures_of_trace(trace: "Trace", config: Config) -> list[Departure]:
    """The departures of a trace's recorded rows (what the run found as it recorded them)."""
    names = [name for name in [TARGET, *trace.vehicles()] if name in trace.channels]
    if not trace.vehicles():
        return []
    data = {name: trace.component(name) for name in names}
    t = data[names[-1]]["t"]
    if any(len(data[name]["t"]) != len(t) for name in names):  # recorded at different instants: vehicles only
        names = [name for name in names if name != TARGET]
    watch = watch_for(config, [(name, WATCHED) for name in names])
    import numpy as np

    watch.add(np.column_stack([t] + [data[name][output] for name in names for output in WATCHED]))
    return watch.result()


def departures_json(departures: list[Departure], config: Config) -> dict:
    """``platoon report --json``'s ``validity``: inside the model or not, the limits, the departures."""
    limits = limits_of(config)
    return {"inside_model": not departures, "min_gap": limits.min_gap,
            "max_speed": [None if math.isinf(v) else v for v in limits.max_speed],
            "departures": [asdict(d) for d in departures]}


def departures_cell(departures: list[Departure]) -> str:
    """A sweep row's ``run.left_model``: "" inside the model, else the kinds, the vehicles and the first time."""
    if not departures:
        return ""
    kinds = ", ".join(f"{kind} ({', '.join(sorted({d.vehicle for d in departures if d.kind == kind}))})"
                      for kind in KINDS if any(d.kind == kind for d in departures))
    return f"{kinds} from t = {min(d.t for d in departures):g} s"


def split_at(departures: list[Departure], start: float) -> tuple[list[Departure], list[Departure]]:
    """(before ``start``, from it on): a run that left the model while it settled (a start far from its own
    equilibrium) and came back measures its gains from the disturbance on; one that leaves it there has none."""
    return [d for d in departures if d.t < start], [d for d in departures if d.t >= start]


def departures_lines(departures: list[Departure], most: int = 6) -> list[str]:
    """What `platoon run`, `stability` and `analyze` print: the departures, the first ``most`` of them."""
    if not departures:
        return []
    lines = [f"LEFT THE MODEL ({len(departures)} departure(s); docs/model.md, section 12): the linear analysis "
             "does not describe this run"]
    lines += [f"  {d.text()}" for d in departures[:most]]
    if len(departures) > most:
        lines.append(f"  ... and {len(departures) - most} more")
    return lines
