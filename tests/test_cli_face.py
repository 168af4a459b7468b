"""The CLI as a newcomer meets it (the console script, in subprocesses): ``platoon --version``; a summary
table that names its units and the interval its max |path error| is taken over, at 80 columns, and
reports what ``report --json`` reports; every ``--help`` naming what its options take; plain progress
lines when the output is a pipe (run, and analyze of 100 vehicles); a warning for a config that runs
but was probably not meant (a platoon longer than its circle, an m3pi slower than V_c)."""

from __future__ import annotations

import json
import os
import re
import subprocess
import sys
from pathlib import Path

from orchestrator import __version__
from tests.test_viewer import PAPER, platoon

FRONT_LATERAL = PAPER.with_name("platoon_front_lateral.toml")


def test_version_prints_the_package_version(tmp_path: Path) -> None:
    result = platoon("--version", cwd=tmp_path)
    assert result.returncode == 0, result.stderr
    assert result.stdout.startswith(f"platoon {__version__} (") and "fmpy" in result.stdout


def test_summary_table_shows_units_and_the_interval_of_the_max_path_error(tmp_path: Path) -> None:
    plain = platoon("run", PAPER, "--set", "simulation.stop_time=1.0", "--out", tmp_path / "a.mcap", cwd=tmp_path)
    assert plain.returncode == 0, plain.stderr
    # rich reads "[m]" as markup and drops it unless escaped; the header may wrap, the units must show
    for unit in ("[m]", "[m/s]"):
        assert unit in plain.stdout
    assert "max |path error|" in plain.stdout and "whole run" in plain.stdout
    assert "means over the last 10% of the recorded time" in plain.stdout
    for line in plain.stdout.splitlines():  # the table fits 80 columns; a path line stays whole (copyable)
        assert len(line) <= 80 or line.startswith(("trace: ", "layout: ")), line
    disturbed = platoon("run", FRONT_LATERAL, "--set", "simulation.stop_time=36.0", "--out", tmp_path / "b.mcap",
                        cwd=tmp_path)
    assert disturbed.returncode == 0, disturbed.stderr
    assert "t >= 35 s" in disturbed.stdout  # from the first disturbance on (orchestrator/analysis/metrics.py)


# The table's headers, as a reader meets them, and the JSON key each one promises (docs/trace-format.md)
TABLE_KEYS = {"path offset": "path_offset", "gap - d*": "gap_error", "speed - V_c": "speed_error",
              "max |path error|": "path_error_max"}


def table_of(stdout: str) -> tuple[list[str], dict[str, list[str]]]:
    """The summary table printed by run/report: its headers (wrapped lines joined) and rows by vehicle."""
    lines = stdout.splitlines()
    header_lines = [line for line in lines if line.startswith("┃")]
    cells = [[cell.strip() for cell in line.strip("┃").split("┃")] for line in header_lines]
    headers = [" ".join(part for part in column if part) for column in zip(*cells)]
    rows = {}
    for line in lines:
        if line.startswith("│ vehicle"):
            values = [cell.strip() for cell in line.strip("│").split("│")]
            rows[values[0]] = values[1:]
    return headers, rows


def test_report_json_and_the_table_report_the_same_quantities(tmp_path: Path) -> None:
    trace = tmp_path / "front.mcap"
    run = platoon("run", FRONT_LATERAL, "--set", "simulation.stop_time=36.0", "--out", trace, cwd=tmp_path)
    assert run.returncode == 0, run.stderr
    table = platoon("report", trace, cwd=tmp_path)
    as_json = platoon("report", trace, "--json", cwd=tmp_path)
    assert table.returncode == 0 and as_json.returncode == 0, table.stderr + as_json.stderr
    report = json.loads(as_json.stdout)
    headers, rows = table_of(table.stdout)
    assert table_of(run.stdout)[1] == rows  # `platoon run` prints the same table as `platoon report`
    assert headers[0] == "vehicle" and len(headers) == 1 + len(TABLE_KEYS)
    keys = []
    for header in headers[1:]:
        match = re.fullmatch(r"(.+?) \[(.+?)\](?:, (.+))?", header)
        assert match, header
        label, unit, interval = match.groups()
        key = TABLE_KEYS[label]
        keys.append(key)
        assert report["units"][key] == unit, (key, unit)  # same unit, stated in the JSON
        if key == "path_error_max":
            assert interval == report["path_error_max_interval"]["text"] == "t >= 35 s"
            assert report["path_error_max_interval"]["from_s"] == 35.0
    assert [v["name"] for v in report["vehicles"]] == list(rows) == ["vehicle1", "vehicle2", "vehicle3", "vehicle4"]
    for vehicle in report["vehicles"]:
        for key, cell in zip(keys, rows[vehicle["name"]]):
            assert cell == (f"{vehicle[key]:.3e}" if key == "path_error_max" else f"{vehicle[key]:+.3e}"), (key, cell)
        # the absolute values beside the deviations: gap - d* and speed - V_c of the recorded config
        assert vehicle["gap"] - 75.0 == vehicle["gap_error"] and vehicle["speed"] - 25.0 == vehicle["speed_error"]
    assert report["steady_window"]["last_fraction"] == 0.1 and "last 10%" in table.stdout


def every_command() -> list[list[str]]:
    """The argument lists that reach each command and group of `platoon` (walked from the click tree)."""
    import typer

    from orchestrator.cli.app import app

    found: list[list[str]] = []

    def walk(command: object, path: list[str]) -> None:
        found.append(path)
        for name, sub in getattr(command, "commands", {}).items():  # a group (typer's own click)
            walk(sub, [*path, name])

    walk(typer.main.get_command(app), [])
    return found


def test_every_help_names_what_its_options_take() -> None:
    """`--help` of every command shows the allowed values of an option with a fixed set (no bare <str>)."""
    from typer.testing import CliRunner

    from orchestrator.cli.app import app
    from orchestrator.execution.run import ENGINES, TRACE_WRITERS

    commands = every_command()
    assert ["run"] in commands and ["bench", "steps"] in commands and ["trace", "recover"] in commands
    assert ["m3pi-emulator"] in commands and ["bench", "hil"] in commands
    runner = CliRunner()
    helps = {}
    for path in commands:
        result = runner.invoke(app, [*path, "--help"], env={"COLUMNS": "100", "NO_COLOR": "1", "TERM": "dumb"})
        assert result.exit_code == 0 and result.exception is None, (path, result.output)
        assert "<str>" not in result.output, (path, result.output)
        assert "<bool>" not in result.output, (path, result.output)  # a flag takes no value
        helps[" ".join(path)] = result.output
    run_help = helps["run"]
    engines = [engine for engine in ENGINES if engine != "monolithic"]  # --monolithic picks that one
    assert f"<{'|'.join(engines)}>" in run_help
    assert f"<{'|'.join(TRACE_WRITERS)}>" in run_help
    assert "KEY=VALUE" in run_help and "KEY=VALUE" in helps["analyze"] and "KEY=VALUE" in helps["m3pi-emulator"]


def progress_lines(stderr: str, label: str, total: int) -> list[int]:
    """The percentages of ``label``'s plain progress lines (orchestrator/observers/progress.py) in ``stderr``."""
    pattern = re.compile(rf"{re.escape(label)}: (\d+)% \((\d+)/{total} steps\), [\d.:]+ (s|min) elapsed(, about .+ left)?")
    found = []
    for line in stderr.splitlines():
        if line.startswith(f"{label}:"):
            match = pattern.fullmatch(line)
            assert match, line
            found.append(int(match.group(1)))
    return found


def piped(*args: object, cwd: Path) -> subprocess.CompletedProcess[str]:
    """``platoon ARGS`` with stdout and stderr pipes (as in CI), a progress line at every tenth."""
    from tests.test_viewer import REPO

    env = {**os.environ, "PYTHONPATH": str(REPO), "PLATOON_PROGRESS_SECONDS": "0", "COLUMNS": "80"}
    for name in ("FORCE_COLOR", "TERM", "NO_COLOR"):
        env.pop(name, None)
    return subprocess.run([sys.executable, "-c", "from orchestrator.cli.app import main; main()", *map(str, args)],
                          cwd=cwd, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, timeout=300)


def test_a_run_in_a_pipe_prints_plain_progress_lines(tmp_path: Path) -> None:
    result = piped("run", PAPER, "--set", "simulation.stop_time=20", "--out", tmp_path / "a.mcap", cwd=tmp_path)
    assert result.returncode == 0, result.stderr
    assert "\x1b" not in result.stderr + result.stdout  # no colour, no cursor movement: a log reads as text
    percents = progress_lines(result.stderr, "simulating", 2000)
    assert len(percents) >= 5 and percents == sorted(set(percents)) and percents[-1] == 100, result.stderr
    assert "trace:" in result.stdout and "simulating" not in result.stdout  # progress on stderr, results on stdout
    # a fresh folder: the FMUs get built first, and the run says so before any progress line
    lines = result.stderr.splitlines()
    building = [k for k, line in enumerate(lines) if line.startswith("building ") and "build/fmus/native/" in line]
    assert len(building) == 2 and building[-1] < lines.index(next(l for l in lines if l.startswith("simulating:"))), lines
    # the estimates count stepping time only: the last line's elapsed time is within the run's own (which
    # excludes the build), to the 0.05 s its one decimal rounds to
    elapsed = float(re.search(r"100% \(2000/2000 steps\), ([\d.]+) s elapsed", result.stderr).group(1))
    run_seconds = float(re.search(r"\(2000 steps in ([\d.]+) s\)", result.stdout).group(1))
    assert elapsed <= run_seconds + 0.05, (elapsed, run_seconds)


def test_analyze_of_a_long_platoon_in_a_pipe_shows_the_progress_of_its_runs(tmp_path: Path) -> None:
    """30 of the bench's 100 vehicles: the progress lines are the same, the linearization a third of the
    CPU (100 vehicles' analysis is test_analysis.py's long-platoon verdict)."""
    hundred = PAPER.parents[1] / "bench" / "platoon100-1h.toml"
    kick = 'disturbance=[{vehicle=1, kind="lateral_acceleration", start=5.0, duration=1.0, value=1.0}]'
    result = piped("analyze", hundred, "--set", "simulation.stop_time=20", "--set", "platoon.count=30", "--set", kick,
                   cwd=tmp_path)
    assert result.returncode == 0, result.stderr
    assert "\x1b" not in result.stderr + result.stdout
    for label in ("disturbed run (1/2)", "undisturbed run (2/2)"):
        percents = progress_lines(result.stderr, label, 200)
        assert len(percents) >= 3 and percents == sorted(set(percents)) and percents[-1] == 100, result.stderr
    assert "string stability" in result.stdout


def test_a_platoon_longer_than_its_circle_is_warned_about_and_still_runs(tmp_path: Path) -> None:
    trace = tmp_path / "seven.mcap"
    result = platoon("run", PAPER, "--set", "platoon.count=7", "--set", "simulation.stop_time=1.0", "--out", trace,
                     cwd=tmp_path)
    assert result.returncode == 0, result.stderr  # a warning, not an error: the run goes
    warnings = [line for line in result.stderr.splitlines() if line.startswith("warning:")]
    assert len(warnings) == 1, result.stderr
    # the numbers (7 x 75 m = 525 m against 2 pi 50 m = 314.2 m) and the keys to change
    for piece in ("7 x 75 m = 525 m", "314.2 m", "platoon.count", "platoon.d_star", "path.radius"):
        assert piece in warnings[0], (piece, warnings[0])
    assert trace.is_file() and "vehicle7" in result.stdout
    bigger_circle = platoon("run", PAPER, "--set", "platoon.count=7", "--set", "path.radius=100",
                            "--set", "simulation.stop_time=1.0", "--out", tmp_path / "fits.mcap", cwd=tmp_path)
    assert bigger_circle.returncode == 0 and "warning:" not in bigger_circle.stderr, bigger_circle.stderr


def test_no_shipped_scenario_is_warned_about() -> None:
    """The paper's configs (and every other shipped scenario) give no warning at all."""
    from orchestrator.scenario.config import load_config
    from orchestrator.scenario.config_warnings import config_warnings

    configs = sorted(PAPER.parents[1].glob("*/*.toml"))
    scenarios = [path for path in configs if path.parent.name not in ("sweeps", "robots")]  # campaigns, robot truths
    assert len(scenarios) >= 9
    for path in scenarios:
        assert config_warnings(load_config(path)[0]) == [], path


def test_an_m3pi_asked_for_more_than_its_wheels_give_is_warned_about(tmp_path: Path) -> None:
    """An m3pi in the paper's 25 m/s platoon (the old docs/config.md example, which failed at 7.24 s)."""
    result = platoon("run", PAPER, "--set", "vehicles.3.dynamics=m3pi", "--set", "simulation.stop_time=1.0",
                     "--out", tmp_path / "m3pi.mcap", cwd=tmp_path)
    assert result.returncode == 0, result.stderr
    warnings = [line for line in result.stderr.splitlines() if line.startswith("warning:")]
    assert len(warnings) == 1 and "vehicle 3 is an m3pi" in warnings[0], result.stderr
    assert "m3pi.wheel_speed_max = 1 m/s" in warnings[0] and "platoon.speed = 25 m/s" in warnings[0]
