"""Runs that leave the model say so (orchestrator/analysis/validity.py, observers/validity.py): collisions,
passes and impossible speeds, found as the rows are recorded, in the run's result and log, and found again
in the trace; runs that stay inside report nothing."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from orchestrator.analysis.validity import (ValidityWatch, departures_cell, departures_of_trace, limits_of,
                                            watch_for)
from orchestrator.execution.run import run_scenario
from orchestrator.trace import load
from tests.conftest import make_config

LINE = {"path": {"kind": "line"}, "platoon": {"count": 2, "d_star": 75.0, "speed": 25.0}}


def rows_of(t: list[float], target_x: list[float], x1: list[float], x2: list[float],
            speeds: tuple[list[float], list[float]] | None = None) -> np.ndarray:
    """Flat rows [t, target (x, y, speed), vehicle1 (...), vehicle2 (...)] on the x axis."""
    n = len(t)
    v1, v2 = speeds if speeds is not None else ([25.0] * n, [25.0] * n)
    return np.column_stack([t, target_x, [0.0] * n, [25.0] * n, x1, [0.0] * n, v1, x2, [0.0] * n, v2])


def watch(**sections) -> ValidityWatch:
    config = make_config(**{**LINE, **sections})
    return watch_for(config, [(name, ("x", "y", "speed")) for name in ("target", "vehicle1", "vehicle2")])


def test_defaults_are_a_vehicle_size_and_three_times_the_speed() -> None:
    assert limits_of(make_config(**LINE)) == limits_of(make_config(**LINE))
    kinematic = limits_of(make_config(**LINE))
    assert kinematic.min_gap == 4.5 and kinematic.max_speed == (75.0, 75.0)
    m3pi = limits_of(make_config(path={"kind": "line"}, platoon={"count": 2, "d_star": 0.3, "speed": 0.2,
                                                                  "dynamics": "m3pi"}))
    assert m3pi.min_gap == 0.095 and all(math.isinf(v) for v in m3pi.max_speed)  # its wheels bound it
    small = limits_of(make_config(path={"kind": "line"}, platoon={"count": 2, "d_star": 2.0, "speed": 1.0}))
    assert small.min_gap == 1.0  # never more than half the equilibrium gap: a small platoon at rest is inside
    stated = limits_of(make_config(**LINE, validity={"min_gap": 10.0, "max_speed": 40.0}))
    assert stated.min_gap == 10.0 and stated.max_speed == (40.0, 40.0)


def test_each_kind_is_found_once_at_its_first_row() -> None:
    w = watch()
    t = [0.0, 1.0, 2.0, 3.0]
    inside = rows_of(t, [150.0, 175, 200, 225], [75.0, 100, 125, 150], [0.0, 25, 50, 75])
    assert w.add(inside) == []
    # vehicle 2 closes in on vehicle 1 (4.5 m at t = 5: at the minimum, a collision), passes it at t = 6, and
    # runs at 80 m/s from t = 5 on
    later = rows_of([4.0, 5.0, 6.0, 7.0], [250.0, 275, 300, 325], [175.0, 200, 225, 250], [160.0, 195.5, 230, 300],
                    ([25.0] * 4, [60.0, 80.0, 90.0, 90.0]))
    found = w.add(later)
    assert [(d.kind, d.vehicle, d.t) for d in found] == [("collision", "vehicle2", 5.0), ("speed", "vehicle2", 5.0),
                                                         ("reversal", "vehicle2", 6.0)]
    assert found[0].ahead == "vehicle1" and found[0].value == pytest.approx(4.5)
    assert found[2].value == pytest.approx(-5.0)
    assert w.add(later) == []  # the first of each kind only
    assert departures_cell(w.result()) == "collision (vehicle2), reversal (vehicle2), speed (vehicle2) from t = 5 s"


def test_a_pass_on_a_circle_is_along_its_direction_of_travel() -> None:
    """Clockwise on a circle of 100 m about the origin: ahead is clockwise."""
    config = make_config(path={"kind": "circle", "radius": 100.0, "direction": "cw"},
                         platoon={"count": 1, "d_star": 50.0})
    w = watch_for(config, [("target", ("x", "y", "speed")), ("vehicle1", ("x", "y", "speed"))])
    ahead, behind = (100.0 * math.cos(-0.5), 100.0 * math.sin(-0.5)), (100.0, 0.0)  # ahead: 0.5 rad clockwise
    inside = np.array([[0.0, *ahead, 25.0, *behind, 25.0]])
    assert w.add(inside) == []
    passed = np.array([[1.0, *behind, 25.0, *ahead, 25.0]])
    assert [d.kind for d in w.add(passed)] == ["reversal"]


PUSHED = {**LINE, "simulation": {"stop_time": 12.0, "step": 0.05, "trace_every": 2},
          "disturbance": [{"vehicle": 2, "kind": "speed", "start": 2.0, "duration": 3.0, "value": 15.0}],
          "validity": {"min_gap": 60.0, "max_speed": 42.0}}


@pytest.mark.parametrize("engine", ["native", "python"])
def test_a_run_finds_them_logs_them_and_the_trace_says_the_same(engine: str, tmp_path: Path, fmu_dir: Path,
                                                               native_fmu_dir: Path) -> None:
    """Vehicle 2 pushed 15 m/s faster for 3 s closes on vehicle 1 to 59.2 m (below the stated 60 m), and vehicle
    1, whose speed is V d*/d of that gap, runs at up to 43.4 m/s (beyond the stated 42); vehicle 2, at 40 m/s,
    stays below it. Every engine finds the same, the run's log says it at the time, `report` finds it again."""
    config = make_config(**PUSHED, name="pushed")
    out = tmp_path / f"{engine}.mcap"
    folder = native_fmu_dir.parent if engine == "native" else fmu_dir
    result = run_scenario(config, "", out, engine=engine, fmu_dir=folder)
    assert result.status == "completed", result.error
    found = {(d.kind, d.vehicle): d for d in result.departures}
    assert set(found) == {("collision", "vehicle2"), ("speed", "vehicle1")}
    collision, speed = found["collision", "vehicle2"], found["speed", "vehicle1"]
    assert 2.0 < collision.t < 5.0 and 59.0 < collision.value <= 60.0 and collision.ahead == "vehicle1"
    assert 2.0 < speed.t < 6.0 and 42.0 < speed.value < 43.5
    trace = load(out)
    assert departures_of_trace(trace, config) == result.departures
    logged = [line for line in trace.log if line.message.startswith("left the model")]
    assert [line.level for line in logged] == ["Warning"] * len(result.departures)
    assert [line.t for line in logged] == pytest.approx([d.t for d in result.departures], abs=1e-9)  # ns stamps
    assert [line.message for line in logged] == [f"left the model: {d.text()}" for d in result.departures]


def test_a_run_that_stays_inside_reports_nothing(tmp_path: Path, native_fmu_dir: Path) -> None:
    config = make_config(**{**PUSHED, "validity": {}}, name="inside")  # the defaults: 4.5 m, 75 m/s
    result = run_scenario(config, "", tmp_path / "inside.mcap", fmu_dir=native_fmu_dir.parent)
    assert result.status == "completed" and result.departures == []
    assert not [line for line in load(tmp_path / "inside.mcap").log if "left the model" in line.message]
