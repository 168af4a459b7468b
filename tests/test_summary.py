"""`platoon run` prints its summary from the rows it recorded, without reading its trace again, and
the numbers are those `platoon report` computes from the trace.

Both sides sum the same float64 deviations, which reach them in blocks of different sizes; the summary sums
the steady window in fixed groups of rows by their index (metrics.SUM_GROUP), so the additions are the same
and the two agree bit for bit (the run stores its summary in the trace for `platoon report` to print:
tests/test_stored_summary.py).
"""

from __future__ import annotations

from dataclasses import astuple

import pytest
from typer.testing import CliRunner

import orchestrator.trace
from orchestrator.cli.app import app
from orchestrator.scenario.config import load_config
from orchestrator.analysis.metrics import summarize
from orchestrator.execution.run import run_scenario
from orchestrator.trace import load
from tests.conftest import REPO, SPEED_TO_ZERO

PLATOON = REPO / "configs" / "paper" / "platoon.toml"
LATERAL = REPO / "configs" / "paper" / "platoon_front_lateral.toml"


def _agree(ours, theirs) -> None:
    assert [s.name for s in ours] == [s.name for s in theirs]
    for a, b in zip(ours, theirs):
        assert astuple(a) == astuple(b), (a, b)  # nan (no disturbance window) never occurs in these runs


@pytest.mark.parametrize("engine", ["native", "python"])
@pytest.mark.parametrize("every", [1, 7])  # 7 does not divide the 2000 steps: the window's end moves
@pytest.mark.parametrize("config_path", [PLATOON, LATERAL], ids=["platoon", "front_lateral"])
@pytest.mark.parametrize("writer", ["inline", "process"])  # the summary folds in the stepping thread, or on its own
def test_run_summary_equals_the_report_of_its_trace(tmp_path, fmu_dir, engine, every, config_path, writer):
    config, text = load_config(config_path, ["simulation.stop_time=40.0", f"simulation.trace_every={every}"])
    out = tmp_path / "run.mcap"
    result = run_scenario(config, text, out, engine=engine, fmu_dir=fmu_dir, summarize=True, trace_writer=writer)
    assert result.status == "completed"
    assert result.summary is not None
    _agree(result.summary, summarize(load(out), config))


def test_a_run_that_stops_early_has_no_running_summary(tmp_path, fmu_dir):
    """Its steady window is not the planned one (the CLI prints no table for a failed run anyway)."""
    failing = tmp_path / "failing.toml"
    failing.write_text(PLATOON.read_text() + SPEED_TO_ZERO)
    config, text = load_config(failing, ["simulation.stop_time=5.0"])
    result = run_scenario(config, text, tmp_path / "run.mcap", fmu_dir=fmu_dir, summarize=True)
    assert result.status == "failed"
    assert result.summary is None


def test_platoon_run_prints_its_table_without_reading_the_trace(tmp_path, fmu_dir, monkeypatch):
    def no_reading(path):
        raise AssertionError(f"the trace {path} was read again")

    monkeypatch.setattr(orchestrator.trace, "load", no_reading)
    out = tmp_path / "run.mcap"
    result = CliRunner().invoke(app, ["run", str(PLATOON), "--set", "simulation.stop_time=20.0", "--out", str(out)])
    assert result.exit_code == 0, result.output
    assert "vehicle4" in result.output and "max |path error|" in result.output
    monkeypatch.undo()
    config, _ = load_config(PLATOON, ["simulation.stop_time=20.0"])
    last = summarize(load(out), config)[-1]
    assert f"{last.path_offset:+.3e}" in result.output


def test_a_failure_of_the_folding_thread_reaches_the_run_and_never_holds_it() -> None:
    """With its trace in a worker process, a run's summary folds on a thread of its own
    (observers/summary.py): what it raises is raised by
    ``finish`` in the run's thread, and blocks handed over after the failure are still taken (more than
    the queue holds), so the run goes on to finish instead of waiting forever."""
    import threading

    import numpy as np

    from orchestrator.observers.summary import PENDING_BLOCKS, SummaryObserver

    config, _ = load_config(PLATOON)
    components = [("target", ["x", "y"]), ("vehicle1", ["x", "y", "gap", "speed"])]
    observer = SummaryObserver(config, components, steps=100, every=1, on_thread=True)
    width = 1 + 2 + 4
    done = threading.Event()

    def feed() -> None:
        observer.block(np.zeros(width + 1))  # not a whole row: the fold's reshape refuses it
        for _ in range(3 * PENDING_BLOCKS):
            observer.block(np.zeros((4, width)))
        done.set()

    feeder = threading.Thread(target=feed, daemon=True)
    feeder.start()
    assert done.wait(timeout=60), "the run waited on a folding thread that had failed"
    with pytest.raises(ValueError, match="reshape"):
        observer.finish()
    observer.finish()  # raised once; finishing again is quiet


@pytest.mark.parametrize("seed", [1, 2, 3])
def test_the_summary_does_not_depend_on_how_the_rows_are_split(seed: int) -> None:
    """The same rows in blocks of any sizes (a run's: 500 or fewer; a trace's: 4096), with rows near the steady
    window's predicted start held back until the end: the same sums, bit for bit."""
    import numpy as np

    from orchestrator.analysis.metrics import running_summary
    from tests.conftest import make_config

    config = make_config(platoon={"count": 3, "d_star": 75.0, "speed": 25.0})
    components = [(name, ("x", "y", "gap", "speed")) for name in ("target", "vehicle1", "vehicle2", "vehicle3")]
    draw = np.random.default_rng(seed)
    count = 5000 + int(draw.integers(0, 3000))
    rows = np.column_stack([np.arange(count) * 0.01, draw.normal(50.0, 5.0, (count, 16))])
    end, step = float(rows[-1, 0]), 0.01

    def summed(cuts: list[int], margin: float):
        summary = running_summary(config, components, 0.0, end, margin)
        for block in np.split(rows, cuts):
            summary.add(block)
        return summary.result()

    whole = summed([], 1e-9 * (end + 1.0))
    for _ in range(5):
        cuts = sorted(int(c) for c in draw.integers(1, count, int(draw.integers(1, 40))))
        assert summed(cuts, 0.5 * step) == whole  # the run's margin: a boundary row held back
        assert summed(list(range(500, count, 500)), 0.5 * step) == whole
