"""The validity watch's plain-Python screen (orchestrator/analysis/validity.py, ``plainly_inside``): what it
passes, numpy's ``add`` finds nothing in; near a limit it defers, so a run's verdicts are numpy's whether
numpy is loaded or not (a quiet run does not load it: tests/test_startup.py)."""

from __future__ import annotations

import math
import random
from pathlib import Path

import numpy as np
import pytest

from orchestrator.analysis.validity import watch_for
from orchestrator.execution.run import run_scenario
from orchestrator.observers import validity as observer
from orchestrator.trace import load
from tests.conftest import make_config

WATCHED = ("x", "y", "speed")


def _rows(rng: random.Random, count: int, vehicles: int, radius: float, d_star: float,
          speed: float) -> list[list[float]]:
    """Rows [t, target, vehicles...] on a circle about (3, -2), each gap near d* or near 0, each speed near
    the limit or a pass: scattered around every threshold, with some exactly on one."""
    rows = []
    for index in range(count):
        angle, row = rng.uniform(0, 2 * math.pi), [float(index)]
        for _ in range(vehicles + 1):
            r = radius * (1 + rng.choice([0.0, 1e-12, rng.uniform(-0.01, 0.01)]))
            fast = rng.choice([3 * speed, -3 * speed, 3 * speed * (1 + 1e-15), rng.uniform(-80.0, 80.0)])
            row += [3.0 + r * math.cos(angle), -2.0 + r * math.sin(angle), speed if rng.random() < 0.8 else fast]
            step = d_star / radius if rng.random() < 0.8 else rng.choice([4.5 / radius, 0.0, -1e-9, 1e-15,
                                                                         rng.uniform(-0.1, 0.5)])
            angle -= step
        rows.append(row)
    return rows


@pytest.mark.parametrize("direction", ["ccw", "cw"])
def test_what_the_screen_passes_numpy_finds_nothing_in(direction: str) -> None:
    config = make_config(path={"kind": "circle", "radius": 50.0, "center": [3.0, -2.0], "direction": direction},
                         platoon={"count": 3, "d_star": 10.0, "speed": 25.0})
    components = [(name, WATCHED) for name in ("target", "vehicle1", "vehicle2", "vehicle3")]
    rng = random.Random(57)
    passed = deferred = 0
    for _ in range(3000):
        rows = _rows(rng, rng.choice([1, 2]), 3, 50.0, 10.0, 25.0)
        if direction == "cw":  # the same rows the other way round: the platoon travels clockwise
            rows = [[row[0], *[v if i % 3 != 1 else 2 * -2.0 - v for i, v in enumerate(row[1:])]] for row in rows]
        if watch_for(config, components).plainly_inside(rows):
            passed += 1
            assert watch_for(config, components).add(np.array(rows)) == [], rows
        else:
            deferred += 1
    assert passed > 100 and deferred > 100  # both sides were tried


def test_a_line_and_exact_limits_defer() -> None:
    config = make_config(path={"kind": "line", "heading": 0.3}, platoon={"count": 1, "d_star": 75.0, "speed": 25.0})
    watch = watch_for(config, [("target", WATCHED), ("vehicle1", WATCHED)])
    c, s = math.cos(0.3), math.sin(0.3)
    assert watch.plainly_inside([[0.0, 75 * c, 75 * s, 25.0, 0.0, 0.0, 25.0]])
    assert not watch.plainly_inside([[0.0, 4.5 * c, 4.5 * s, 25.0, 0.0, 0.0, 25.0]])  # the minimum gap, exactly
    assert not watch.plainly_inside([[0.0, 75 * c, 75 * s, 25.0, 0.0, 0.0, 75.0 + 1e-12]])  # above 3 V_c
    assert watch.plainly_inside([[0.0, 75 * c, 75 * s, 25.0, 0.0, 0.0, -75.0]])  # |speed| at the limit is inside
    assert not watch.plainly_inside([[0.0, 75 * c, 75 * s, 25.0, math.nan, 0.0, 25.0]])  # not finite: numpy decides
    assert not watch.plainly_inside([[0.0, -75 * s, 75 * c, 25.0, 0.0, 0.0, 25.0]])  # beside it: along = 0


PUSHED = {"path": {"kind": "line"}, "platoon": {"count": 2, "d_star": 75.0, "speed": 25.0},
          "simulation": {"stop_time": 12.0, "step": 0.05, "trace_every": 2},
          "disturbance": [{"vehicle": 2, "kind": "speed", "start": 2.0, "duration": 3.0, "value": 15.0}]}


@pytest.mark.parametrize("engine", ["native", "python"])
@pytest.mark.parametrize("stated, passed", [({"min_gap": 60.0, "max_speed": 42.0}, 0), ({}, 1)])
def test_a_run_without_numpy_finds_what_numpy_finds(engine: str, stated: dict, passed: int, tmp_path: Path,
                                                    monkeypatch: pytest.MonkeyPatch, fmu_dir: Path,
                                                    native_fmu_dir: Path) -> None:
    """The runs of tests/test_validity.py that leave the model (the screen defers) and stay inside (it passes),
    with the observer's numpy check off (as in a quiet run's process) and on: the same departures and log."""
    config = make_config(**{**PUSHED, "validity": stated}, name="pushed")
    folder = native_fmu_dir.parent if engine == "native" else fmu_dir
    with_numpy = run_scenario(config, "", tmp_path / "numpy.mcap", engine=engine, fmu_dir=folder)
    screened: list[int] = []
    plainly_inside = observer.ValidityObserver._plainly_inside

    def counted(self, rows, count):  # the screen did run (and deferred some blocks, passed others)
        screened.append(int(plainly_inside(self, rows, count)))
        return bool(screened[-1])

    monkeypatch.setattr(observer, "numpy_loaded", lambda: False)
    monkeypatch.setattr(observer.ValidityObserver, "_plainly_inside", counted)
    plain = run_scenario(config, "", tmp_path / "plain.mcap", engine=engine, fmu_dir=folder)
    expected = {("collision", "vehicle2"), ("speed", "vehicle1")} if stated else set()
    assert {(d.kind, d.vehicle) for d in with_numpy.departures} == expected
    assert plain.departures == with_numpy.departures
    assert screened and set(screened) == {passed}
    logs = [[(line.t, line.message) for line in load(tmp_path / name).log if "left the model" in line.message]
            for name in ("numpy.mcap", "plain.mcap")]
    assert logs[0] == logs[1] and bool(logs[0]) == bool(stated)
