"""The ``platoon`` command end to end: the installed console script, run in real subprocesses.

Covers the promises of orchestrator/cli/ and docs/config.md: a bad config or bad input exits 2
with one ``error:`` line naming the key and value and no traceback; a run exits 0, writes its trace
and prints the summary; ``report`` prints JSON and draws the panels; a run that fails exits 1 and
keeps a readable trace up to the failure.
"""

from __future__ import annotations

import json
import math
import re
import os
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from orchestrator.trace import load
from tests.conftest import SPEED_TO_ZERO

REPO = Path(__file__).resolve().parents[1]
PLATOON = Path(sys.executable).parent / "platoon"
PAPER = REPO / "configs" / "paper" / "platoon.toml"
SHORT = ("--set", "simulation.stop_time=2.0")
VEHICLES = ["vehicle1", "vehicle2", "vehicle3", "vehicle4"]
SUMMARY_KEYS = {"name", "path_offset", "gap", "gap_error", "speed", "speed_error", "path_error_max"}


def platoon(*args: object, cwd: Path, timeout: float = 120) -> subprocess.CompletedProcess[str]:
    """Run the console script as a user would, without a terminal (no progress bar, no colour)."""
    assert PLATOON.is_file(), f"console script not installed next to the interpreter: {PLATOON}"
    env = {**os.environ, "COLUMNS": "80", "NO_COLOR": "1", "TERM": "dumb", "PYTHONPATH": str(REPO)}  # this tree's code
    env.pop("FORCE_COLOR", None)
    return subprocess.run(
        [str(PLATOON), *map(str, args)], cwd=cwd, env=env, capture_output=True, text=True, timeout=timeout
    )


def error_line(result: subprocess.CompletedProcess[str]) -> str:
    """stderr must be exactly one ``error:`` line and no traceback; returns that line."""
    assert "Traceback" not in result.stderr and "Traceback" not in result.stdout, result.stderr
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1, f"expected one line on stderr, got {len(lines)}:\n{result.stderr}"
    assert lines[0].startswith("error: "), lines[0]
    return lines[0]


@pytest.fixture(scope="module")
def workdir(tmp_path_factory: pytest.TempPathFactory, fmu_dir: Path, native_fmu_dir: Path) -> Path:
    """Current folder of every call, holding the FMUs in ./build/fmus as a first run leaves them: the
    tests that expect exactly one line on stderr must not depend on which of them runs first (a first
    run says it builds them)."""
    folder = tmp_path_factory.mktemp("cli")
    for built, where in ((fmu_dir, folder / "build" / "fmus"), (native_fmu_dir, folder / "build" / "fmus" / "native")):
        where.mkdir(parents=True, exist_ok=True)
        for fmu in built.glob("*.fmu"):
            shutil.copy2(fmu, where / fmu.name)
    return folder


def write_config(folder: Path, name: str, text: str) -> Path:
    path = folder / name
    path.write_text(text)
    return path


# --- bad input: exit 2, one line naming key and value -----------------------------------------

DISTURBANCE_ON_VEHICLE_5 = """
[platoon]
count = 4

[[disturbance]]
vehicle = 5
kind = "speed"
start = 1.0
duration = 1.0
value = 5.0
"""

BAD_CONFIGS = {
    # id: (config file text or None for configs/paper/platoon.toml, --set overrides, expected pieces)
    "unknown-key-set": (None, ["platoon.colour=red"], ["platoon.colour: unknown key"]),  # nothing near: no guess
    "unknown-section-file": ("[platon]\ncount = 4\n", [], ["platon", "unknown key (did you mean platoon?)"]),
    "mistyped-key": (None, ["platoon.cout=3"], ["platoon.cout: unknown key (did you mean platoon.count?)"]),
    "mistyped-vehicle-key": (None, ["vehicles.2.endpont=zenoh"], ["(did you mean vehicles.2.endpoint?)"]),
    "heading-in-degrees": (None, ["path.heading=90"], ["path.heading = 90", "<= 6.28319 rad", "90 degrees = 1.5708 rad"]),
    "speed-zero": (None, ["platoon.speed=0"], ["platoon.speed = 0", ">= 0.001 m/s and <= 1000 m/s"]),
    "count-string": (None, ['platoon.count="four"'], ["platoon.count", "'four'", "integer"]),
    "count-float": (None, ["platoon.count=2.5"], ["platoon.count", "2.5", "integer"]),
    "count-bool": ("[platoon]\ncount = true\n", [], ["platoon.count", "True", "integer"]),
    "d-star-over-diameter": (None, ["platoon.d_star=150"], ["platoon.d_star", "150", "2 * path.radius = 100"]),
    "radius-too-small": ("[path]\nradius = 10.0\n[platoon]\nd_star = 25.0\n", [], ["platoon.d_star", "25.0", "2 * path.radius = 20"]),
    "count-zero": (None, ["platoon.count=0"], ["platoon.count", "= 0", "must be an integer >= 1"]),
    "step-negative": (None, ["simulation.step=-0.01"], ["simulation.step", "-0.01", "must be a finite number > 0 s"]),
    "step-over-stop": (None, ["simulation.stop_time=0.001"], ["simulation.step", "simulation.stop_time"]),
    "disturbance-vehicle-5": (DISTURBANCE_ON_VEHICLE_5, [], ["disturbance[0].vehicle", "5", "platoon.count = 4"]),
    "override-vehicle-7": (None, ["vehicles.7.law=sine"], ["vehicles.7", "platoon.count = 4"]),
    "unknown-law": (None, ["platoon.law=zigzag"], ["platoon.law", "zigzag", "'sine' or 'regular'"]),
    "unknown-master": (None, ["simulation.master=gauss_seidel"], ["simulation.master", "gauss_seidel", "jacobi"]),
    "set-without-equals": (None, ["platoon.count"], ["--set", "platoon.count", "KEY=VALUE"]),
    "set-through-value": (None, ["platoon.count.x=1"], ["--set", "platoon.count is not a table"]),
    "initial-incomplete": (None, ["vehicles.1.initial={x=1.0}"], ["vehicles.1.initial.y", "missing"]),
    "invalid-toml": ("[platoon\ncount = 4\n", [], ["not valid TOML"]),
}


@pytest.mark.parametrize("case", list(BAD_CONFIGS), ids=list(BAD_CONFIGS))
def test_bad_config_exits_2_with_one_clear_line(case: str, workdir: Path, tmp_path: Path) -> None:
    text, overrides, expected = BAD_CONFIGS[case]
    config = PAPER if text is None else write_config(tmp_path, f"{case}.toml", text)
    sets = [arg for value in overrides for arg in ("--set", value)]
    result = platoon("run", config, *sets, "--out", tmp_path / "never.mcap", cwd=workdir)
    assert result.returncode == 2, result.stderr
    line = error_line(result)
    assert line.startswith(f"error: config {config}: "), line
    for piece in expected:
        assert piece in line, f"{piece!r} missing from {line!r}"
    assert not (tmp_path / "never.mcap").exists()


def test_missing_config_file_exits_2(workdir: Path, tmp_path: Path) -> None:
    missing = tmp_path / "nonexistent.toml"
    result = platoon("run", missing, cwd=workdir)
    assert result.returncode == 2
    line = error_line(result)
    assert str(missing) in line and "No such file" in line, line


@pytest.mark.parametrize("option, value, expected", [
    ("--out", "{file}/inside.mcap", "--out {file}/inside.mcap: cannot write there: Not a directory"),
    ("--trace-writer", "threads", "--trace-writer 'threads': expected one of auto, inline, process"),
    ("--engine", "fortran", "--engine 'fortran': expected native or python"),
    ("--engine", "natve", "--engine 'natve': expected native or python (did you mean native?)"),
    ("--fmus", "c", "--fmus 'c': expected native or python"),  # the option's error, not simulation.fmus's
])
def test_bad_run_option_exits_2_with_one_clear_line(option: str, value: str, expected: str, workdir: Path,
                                                    tmp_path: Path) -> None:
    (tmp_path / "file").write_text("a file, not a folder")
    value = value.format(file=tmp_path / "file")
    expected = expected.format(file=tmp_path / "file")
    arguments = [option, value] if option == "--out" else [option, value, "--out", tmp_path / "never.mcap"]
    result = platoon("run", PAPER, *SHORT, *arguments, cwd=workdir)
    assert result.returncode == 2, result.stderr
    assert expected in error_line(result)
    assert not (tmp_path / "never.mcap").exists()


# --- a run, its summary, its report ------------------------------------------------------------

@pytest.fixture(scope="module")
def completed_run(workdir: Path) -> tuple[subprocess.CompletedProcess[str], Path]:
    trace = workdir / "runs" / "platoon-short.mcap"
    return platoon("run", PAPER, *SHORT, "--out", trace, cwd=workdir), trace


def test_run_writes_trace_and_prints_summary(completed_run) -> None:
    result, trace = completed_run
    assert result.returncode == 0, result.stderr
    assert "Traceback" not in result.stderr
    assert trace.is_file() and trace.stat().st_size > 0
    for piece in ["path offset", "gap - d*", "speed - V_c", "max |path error|", *VEHICLES, f"trace: {trace}"]:
        assert piece in result.stdout, f"{piece!r} missing from:\n{result.stdout}"
    loaded = load(trace)
    assert loaded.run["status"] == "completed"
    assert loaded.vehicles() == VEHICLES
    assert loaded.config["simulation"]["stop_time"] == 2.0  # the --set override is what was run
    for name in ["target", *VEHICLES]:
        t = loaded.component(name)["t"]
        assert len(t) == 201 and t[0] == 0.0 and t[-1] == pytest.approx(2.0)


def test_report_json(completed_run, workdir: Path) -> None:
    _, trace = completed_run
    result = platoon("report", trace, "--json", cwd=workdir)
    assert result.returncode == 0, result.stderr
    report = json.loads(result.stdout)
    assert list(report) == ["trace", "law", "status", "units", "steady_window", "path_error_max_interval", "vehicles",
                            "validity", "links"]
    assert report["links"] == []  # the paper's platoon has no communication links
    # vehicle 1 starts 5 m off the circle and swings in: no vehicle comes within 4.5 m of another, or passes it
    assert report["validity"] == {"inside_model": True, "min_gap": 4.5, "max_speed": [75.0] * len(VEHICLES),
                                  "departures": []}
    assert [v["name"] for v in report["vehicles"]] == VEHICLES
    for vehicle in report["vehicles"]:
        assert set(vehicle) == SUMMARY_KEYS
        assert all(math.isfinite(vehicle[k]) for k in SUMMARY_KEYS - {"name"})
        assert vehicle["gap"] > 0 and vehicle["speed"] > 0 and vehicle["path_error_max"] >= 0
    # vehicle 1 starts 5 m outside the circle (configs/paper/platoon.toml), so its largest path error is 5 m
    assert report["vehicles"][0]["path_error_max"] == pytest.approx(5.0, rel=1e-6)


def test_report_plots(completed_run, workdir: Path, tmp_path: Path) -> None:
    _, trace = completed_run
    plots = tmp_path / "plots"
    result = platoon("report", trace, "--plots", plots, cwd=workdir)
    assert result.returncode == 0, result.stderr
    assert "vehicle4" in result.stdout  # the table, then the files
    for name in ["speed_errors.png", "gap_errors.png", "path_errors.png", "xy.png"]:
        png = plots / name
        assert png.is_file() and png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n", png
        # at 80 columns a long path wraps onto the next line (a parallel worker's tmp folder is longer)
        assert str(png) in result.stdout.replace("\n", "")
    assert_plots_show_the_trace(load(trace), plots, tmp_path / "again")


def panel_series(trace, config) -> dict:
    """What each time panel draws for a vehicle, from the trace (by file stem): the paper's errors."""
    from orchestrator.analysis.metrics import path_errors

    return {
        "speed_errors": lambda v: trace.component(v)["speed"] - config.platoon.speed,
        "gap_errors": lambda v: trace.component(v)["gap"] - config.platoon.d_star,
        "path_errors": lambda v: path_errors(config, trace.component(v)["x"], trace.component(v)["y"]),
    }


def assert_plots_show_the_trace(trace, written: Path, scratch: Path) -> None:
    """What the panels draw is the trace's data (each vehicle's speed - V_c, gap - d*, signed path
    error over time; its x, y), and the PNGs in ``written`` show exactly those figures: the same
    drawing, made here with its figures kept, gives the same pixels."""
    import matplotlib.image

    from orchestrator.analysis import plots as plots_module
    from orchestrator.scenario.config import config_from_mapping

    config = config_from_mapping(trace.config)
    kept = []
    close = plots_module.plt.close
    plots_module.plt.close = kept.append  # write_plots closes each figure once saved: keep them instead
    try:
        again = plots_module.write_plots(trace, config, scratch)
    finally:
        plots_module.plt.close = close
    expected = panel_series(trace, config)
    for figure, png in zip(kept, again):
        (axes,) = [a for a in figure.axes if a.get_label() != "<colorbar>"]
        lines = axes.get_lines()
        for k, vehicle in enumerate(VEHICLES):
            channel = trace.component(vehicle)
            if png.stem in expected:  # a line per vehicle, in order
                assert np.array_equal(lines[k].get_xdata(), channel["t"]), (png.name, vehicle)
                assert np.array_equal(lines[k].get_ydata(), expected[png.stem](vehicle)), (png.name, vehicle)
            else:  # the path first, then each vehicle's track and its end
                track = lines[1 + 2 * k]
                assert np.array_equal(track.get_xdata(), channel["x"]) and np.array_equal(track.get_ydata(), channel["y"])
        shown = matplotlib.image.imread(written / png.name)
        assert np.array_equal(shown, matplotlib.image.imread(png)), f"{png.name}: the command's PNG shows another figure"
        close(figure)
    assert [p.name for p in again] == ["speed_errors.png", "gap_errors.png", "path_errors.png", "xy.png"]


# --- report on bad input: exit 2 ------------------------------------------------------------------

def test_report_missing_trace_exits_2(workdir: Path, tmp_path: Path) -> None:
    missing = tmp_path / "nothing.mcap"
    result = platoon("report", missing, cwd=workdir)
    assert result.returncode == 2
    line = error_line(result)
    assert str(missing) in line and "no such file" in line, line


def test_report_non_mcap_file_exits_2(workdir: Path, tmp_path: Path) -> None:
    bogus = write_config(tmp_path, "bogus.mcap", "this is not an MCAP file\n")
    result = platoon("report", bogus, cwd=workdir)
    assert result.returncode == 2
    line = error_line(result)
    assert str(bogus) in line and "not a readable MCAP trace" in line, line


def test_report_mcap_without_platoon_metadata_exits_2(workdir: Path, tmp_path: Path) -> None:
    from mcap.writer import Writer

    foreign = tmp_path / "foreign.mcap"
    with open(foreign, "wb") as stream:
        writer = Writer(stream)
        writer.start()
        writer.finish()
    result = platoon("report", foreign, cwd=workdir)
    assert result.returncode == 2
    line = error_line(result)
    assert str(foreign) in line and "platoon.config" in line, line


# --- a run that fails: exit 1, trace kept up to the failure --------------------------------------

def test_run_failure_at_start_exits_1_and_keeps_trace(workdir: Path, tmp_path: Path) -> None:
    """Vehicle 1 placed exactly on its target, the virtual target's start point (R, 0): distance 0."""
    trace = tmp_path / "on-target.mcap"
    result = platoon(
        "run", PAPER, *SHORT, "--set", "vehicles.1.initial={x=50.0, y=0.0, heading=1.5707963267948966, speed=20.0}",
        "--out", trace, cwd=workdir,
    )
    assert result.returncode == 1, result.stderr
    line = error_line(result)
    assert "run failed" in line and "at t = 0 s" in line, line
    assert "target" in line or "vehicle1" in line, line  # the component
    assert str(trace) in line
    loaded = load(trace)  # readable, though nothing could be recorded
    assert loaded.run["status"] == "failed"
    assert "t = 0 s" in loaded.run["error"]
    assert loaded.run["steps_recorded"] == "0"
    assert loaded.config["vehicles"]["1"]["initial"]["x"] == 50.0




def test_run_failure_mid_run_exits_1_and_keeps_trace(workdir: Path, tmp_path: Path) -> None:
    """A -100 m/s speed disturbance on vehicle 4 at t = 1 s: its speed goes negative in the next step."""
    config = write_config(tmp_path, "speed_to_zero.toml", PAPER.read_text() + SPEED_TO_ZERO)
    trace = tmp_path / "speed-to-zero.mcap"
    result = platoon("run", config, *SHORT, "--out", trace, cwd=workdir)
    assert "Traceback" not in result.stderr
    assert result.stderr.startswith("error: run failed: vehicle4 failed at t = 1 s"), result.stderr
    assert str(trace) in result.stderr
    loaded = load(trace)
    assert loaded.run["status"] == "failed"
    assert loaded.run["error"].startswith("vehicle4 failed at t = 1 s")
    assert loaded.run["steps_recorded"] == "101"
    for name in ["target", *VEHICLES]:  # every communication point from 0 to 1 s, nothing after
        t = loaded.component(name)["t"]
        assert len(t) == 101 and t[-1] == pytest.approx(1.0)
    assert result.returncode == 1, result.returncode
    assert "speed fell" in loaded.run["error"], loaded.run["error"]
    assert len(result.stderr.strip().splitlines()) == 1, result.stderr
    report = platoon("report", trace, cwd=workdir)  # the summary of what it recorded says how far the run got
    assert report.returncode == 0 and "(failed at t = 1 of 2 s)" in " ".join(report.stdout.split()), report.stdout


def test_run_verbose_splits_the_wall_time_from_the_process_start(tmp_path):
    result = platoon("run", REPO / "configs" / "paper" / "single.toml", "--set", "simulation.stop_time=0.5",
                     "--out", tmp_path / "t.mcap", "-q", "-v", cwd=REPO)
    assert result.returncode == 0, result.stderr
    lines = [line.strip() for line in result.stderr.splitlines()]
    total = next(line for line in lines if line.startswith("wall time since the process started:"))
    assert re.fullmatch(r"wall time since the process started: \d+\.\d\d s", total), total
    for piece in ("interpreter and imports", "config", "run modules imported", "FMUs checked and unpacked", "run: setup", "initialize",
                  "steps", "finish", "after the run"):
        assert re.search(re.escape(piece) + r"[^0-9?]*\d+\.\d\d s", result.stderr), piece
    first = re.search(r"the first step began (\d+\.\d\d) s after the process started", result.stderr)
    assert first is not None and 0 < float(first.group(1)) <= float(total.split(": ")[1][:-2]), result.stderr
