"""The trace writer process started before the run knows its config: it holds the trace's lock once
the run shares it, and `platoon run` starts it early only when the run will want it
(orchestrator/trace/worker.py: TraceProcess, prestart; orchestrator/cli/trace_forecast.py)."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

from orchestrator.cli.launch import plain_run_options
from orchestrator.cli.trace_forecast import wants_trace_worker
from orchestrator.support.output import OutputError
from orchestrator.trace import load
from orchestrator.trace.output import check_in_use, claim
from orchestrator.trace.worker import TraceProcess, TraceWorker

ROOT = Path(__file__).resolve().parents[1]
PAPER = ROOT / "configs" / "paper" / "platoon.toml"  # 10 000 steps of 5 components
PLATOON = Path(sys.executable).parent / "platoon"


def test_the_worker_holds_the_shared_lock_until_it_has_finished_the_file(tmp_path: Path) -> None:
    """The lock travels to a worker started before it existed; the path stays claimed while the worker
    writes, though the stepping process let go of its own descriptor, and is free once it is done."""
    process = TraceProcess()  # started first, as a prestarted one is
    target = claim(tmp_path / "run.mcap")
    process.share(target.fd)
    writer = TraceWorker(target.aside, [("car", ["x"])], process=process)
    target.release()  # the stepping process's own descriptor: as if it had died
    with pytest.raises(OutputError, match="a running run is writing it"):
        check_in_use(target.aside)
    writer.write_block([[0.0, 1.0], [0.1, 2.0]])
    writer.close()
    check_in_use(target.aside)  # the worker exited: nothing holds the lock
    assert load(target.aside).component("car")["x"].tolist() == [1.0, 2.0]


def test_an_unused_early_worker_ends_and_takes_no_lock(tmp_path: Path) -> None:
    process = TraceProcess()
    target = claim(tmp_path / "run.mcap")
    process.share(target.fd)
    process.close()  # the run did not want it: it ends before any argument, and drops what it was given
    target.release()
    check_in_use(target.aside)
    assert process.process.returncode == 0


def _options(*args: str):
    options = plain_run_options(["run", *args])
    assert options is not None
    return options


@pytest.mark.parametrize(("args", "expected"), [
    ((str(PAPER),), True),  # 10 001 rows x 5 components
    ((str(PAPER), "--set", "simulation.stop_time=0.1"), False),  # 11 rows: written in process
    ((str(PAPER), "--trace-every", "100"), False),  # 101 rows x 5
    ((str(PAPER), "--set", "platoon.count=16", "--trace-every", "100"), False),  # 101 x 17 = 1717
    ((str(PAPER), "--set", "platoon.count=100", "--trace-every", "100"), True),  # 101 x 101
    ((str(PAPER), "--trace-writer", "inline"), False),
    ((str(PAPER), "--trace-writer", "process", "--set", "simulation.stop_time=0.1"), True),
])
def test_the_forecast_follows_the_runs_own_choice(args: tuple[str, ...], expected: bool) -> None:
    if expected and "process" not in args and len(os.sched_getaffinity(0)) < 2:
        expected = False  # "auto" writes in process on one core
    assert wants_trace_worker(_options(*args)) is expected


def test_a_config_the_forecast_cannot_read_starts_no_worker(tmp_path: Path) -> None:
    bad = tmp_path / "bad.toml"
    bad.write_text("[simulation\nstop_time = 100.0\n")
    assert wants_trace_worker(_options(str(bad))) is False
    odd = tmp_path / "odd.toml"
    odd.write_text('simulation = "not a table"\n')
    assert wants_trace_worker(_options(str(odd))) is False
    assert wants_trace_worker(_options(str(tmp_path / "missing.toml"))) is False


def test_children_run_this_package_not_a_copy_in_the_current_folder(tmp_path: Path) -> None:
    """A run (its trace worker) and a sweep (its run processes) started from a folder that holds another
    ``orchestrator`` package still run this one: children are started with ``python -P`` and this
    package's folder on PYTHONPATH (orchestrator/support/child_python.py)."""
    impostor = tmp_path / "orchestrator"
    impostor.mkdir()
    (impostor / "__init__.py").write_text('raise ImportError("the copy in the current folder was imported")\n')
    config = tmp_path / "short.toml"
    config.write_text(PAPER.read_text().replace("stop_time = 100.0", "stop_time = 2.0"))
    run = subprocess.run([PLATOON, "run", str(config), "--trace-writer", "process", "--out", str(tmp_path / "run.mcap")],
                         cwd=tmp_path, capture_output=True, text=True, timeout=300)
    assert run.returncode == 0, run.stderr
    assert len(load(tmp_path / "run.mcap").component("vehicle1")["t"]) == 201
    sweep = tmp_path / "sweep.toml"
    sweep.write_text(f'base = "{config}"\n\n[grid]\n"platoon.k_v" = [0.5, 1.0]\n')
    done = subprocess.run([PLATOON, "sweep", str(sweep), "--out", str(tmp_path / "swept")], cwd=tmp_path,
                          capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stderr
    assert "2 runs completed" in done.stdout, done.stdout + done.stderr


def test_a_run_that_writes_in_process_ends_the_early_worker_before_it_steps(tmp_path: Path, fmu_dir: Path) -> None:
    """A worker started on a forecast the run does not confirm (here: --trace-writer inline decided
    later, as a config's live robots do) is ended when the run decides, not left idle for its length."""
    from orchestrator.execution.run import run_scenario
    from orchestrator.scenario.config import load_config
    from orchestrator.trace import worker

    worker.prestart()
    early = worker._prestarted
    assert early is not None
    config, text = load_config(PAPER, ["simulation.stop_time=1.0"])
    at_first_tick: list[int | None] = []

    def tick(steps_done: int) -> None:  # called by the run after its first steps: the worker must be gone by then
        if not at_first_tick:
            try:
                at_first_tick.append(early.process.wait(timeout=30))  # ends at once once told; never if not told
            except subprocess.TimeoutExpired:
                at_first_tick.append(None)

    result = run_scenario(config, text, tmp_path / "run.mcap", fmu_dir=fmu_dir, trace_writer="inline", tick=tick)
    assert result.status == "completed"
    assert at_first_tick == [0], "the early worker was still running when the run stepped"  # saw its inbox close
    assert worker.take_prestarted() is None
