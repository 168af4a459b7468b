"""`platoon run` without typer (orchestrator/cli/launch.py) reads a command line as typer does, or leaves it
to typer.

The console script parses a plainly well-formed `platoon run` itself, to start without typer and rich
(docs/performance.md, "Start-up"). A user must not be able to tell: every command line it accepts
gives the options typer gives, and every one typer refuses (or answers with help) goes to typer.
"""

from __future__ import annotations

from pathlib import Path

import pytest
import typer
from typer.testing import CliRunner

import orchestrator.cli.run as run_module
from orchestrator.cli.app import app
from orchestrator.cli.launch import REPORT_OPTIONS, RUN_OPTIONS, RUN_RANGES, plain_report_options, plain_run_options
from orchestrator.cli.options import RunOptions

C = "configs/paper/platoon.toml"

# command lines after `platoon`: plain ones (the fast start takes them) and others (typer's)
COMMAND_LINES = [
    ["run", C],
    ["run", C, "-q"],
    ["run", "-q", C, "-v"],
    ["run", C, "--out", "runs/x.mcap", "--set", "platoon.count=16", "--set", "simulation.stop_time=0.1", "-q"],
    ["run", C, "--out=runs/x.mcap", "--set=platoon.law=regular", "--trace-every=10"],
    ["run", C, "--trace-every", "1", "--engine", "python", "--fmus", "native", "--trace-writer", "inline"],
    ["run", C, "--trace-every", "010"],
    ["run", C, "--monolithic", "--compare-monolithic", "--overwrite", "--allow-long", "--verbose", "--quiet"],
    ["run", C, "--live", "--live-port", "0", "--live-host", "0.0.0.0", "--live-speed", "2.5", "--live-wait"],
    ["run", C, "--live-port", "65535", "--live-speed", "0"],
    ["run", C, "--live-speed", ".5"],
    ["run", C, "--engine", "java"],  # our own check's message, not typer's
    ["run", C, "-q", "-q"],
    ["run", C, "--set", "a=1", "--set", "a=2", "--set", "b = 'x y'"],
    ["run", "a config with spaces.toml"],
    # typer's: help, errors, or a reading the fast start does not attempt
    ["run"],
    ["run", "--help"],
    ["run", C, "--help"],
    ["run", C, "-h"],
    ["run", C, "extra.toml"],
    ["run", C, "--unknown"],
    ["run", C, "--out"],
    ["run", C, "--trace-every", "0"],
    ["run", C, "--trace-every", "-3"],
    ["run", C, "--trace-every", "x"],
    ["run", C, "--trace-every", "+3"],
    ["run", C, "--trace-every", " 3"],
    ["run", C, "--trace-every", "1_0"],
    ["run", C, "--live-port", "65536"],
    ["run", C, "--live-speed", "-1"],
    ["run", C, "--live-speed", "nan"],
    ["run", C, "--live-speed", "1e3"],
    ["run", C, "--out", "a.mcap", "--out", "b.mcap"],
    ["run", C, "--live-speed", "0", "--live-speed", "0.5"],
    ["run", C, "--out", "-x.mcap"],
    ["run", C, "--out="],
    ["run", C, "-qv"],
    ["run", C, "--quiet=true"],
    ["run", C, "--", "x"],
    ["run", "-"],
    ["run", ""],
    ["--version"],
    ["report", "x.mcap"],
    ["rn", C],
]


def typers_reading(args: list[str], monkeypatch: pytest.MonkeyPatch) -> tuple[int, RunOptions | None]:
    """(exit code, the RunOptions typer's `run` command built) for ``args``; nothing is run."""
    built: list[RunOptions] = []
    monkeypatch.setattr(run_module, "run_command", built.append)
    result = CliRunner().invoke(app, args, env={"COLUMNS": "100", "NO_COLOR": "1", "TERM": "dumb"})
    return result.exit_code, (built[0] if built else None)


@pytest.mark.parametrize("args", COMMAND_LINES, ids=lambda args: " ".join(args) or "(empty)")
def test_the_fast_start_reads_a_command_line_as_typer_does_or_leaves_it_to_typer(
        args: list[str], monkeypatch: pytest.MonkeyPatch) -> None:
    code, typers = typers_reading(args, monkeypatch)
    ours = plain_run_options(args)
    if ours is not None:  # taken without typer: exactly what typer would have run
        assert code == 0 and ours == typers, (code, ours, typers)
    # else typer reads it, as it always did


def test_the_plain_command_lines_above_are_taken_by_the_fast_start() -> None:
    """The cases that matter (what the README, the benchmarks and a sweep's users type) start fast; help,
    errors and the unusual go to typer."""
    plain = COMMAND_LINES[:COMMAND_LINES.index(["run"])]
    assert [args for args in COMMAND_LINES if plain_run_options(args) is not None] == plain


def test_a_shell_completion_request_goes_to_typer(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("_PLATOON_COMPLETE", "bash_complete")
    assert plain_run_options(["run", C]) is None


def test_the_fast_start_knows_every_option_of_the_typer_command_as_declared() -> None:
    """Its table (orchestrator/cli/launch.py) against the command's declaration (orchestrator/cli/run.py):
    the same options, names, kinds and ranges, so a new option cannot be forgotten there."""
    command = typer.main.get_command(app).commands["run"]  # type: ignore[attr-defined]
    declared: dict[str, tuple[str, str]] = {}
    ranges: dict[str, tuple[object, object]] = {}
    kinds = {Path: "path", list[str]: "list", bool: "flag", int: "int", float: "float", str: "text"}
    for param in command.params:
        if param.param_type_name == "argument":
            assert param.name == "config"
            continue
        for name in param.opts:
            declared[name] = (param.name, kinds[param.type_descriptor.annotation])
        if param.min is not None or param.max is not None:
            ranges[param.name] = (param.min, param.max)
    fields = set(RunOptions.__dataclass_fields__)
    assert declared == RUN_OPTIONS and set(name for name, _ in declared.values()) | {"config"} == fields
    assert ranges == RUN_RANGES
    defaults = {param.name: param.default for param in command.params if param.name != "config"}
    assert {name: list(value) if isinstance(value, tuple) else value for name, value in defaults.items()} == \
        {name: getattr(RunOptions(Path(C)), name) for name in defaults}


# `platoon report` command lines: plain ones first (the fast start takes them), then typer's
T = "runs/x.mcap"
REPORT_LINES = [
    ["report", T],
    ["report", T, "--json"],
    ["report", "--json", T, "--plots", "runs/plots", "--overwrite"],
    ["report", T, "--plots=runs/plots"],
    ["report", "a trace with spaces.mcap"],
    ["report", T, "--json", "--json"],
    # typer's
    ["report"],
    ["report", "--help"],
    ["report", T, "-h"],
    ["report", T, "other.mcap"],
    ["report", T, "--json=true"],
    ["report", T, "--plots"],
    ["report", T, "--plots", ""],
    ["report", T, "--plots", "-x"],
    ["report", T, "--csv", "x"],
    ["report", T, "--", "x"],
    ["report", ""],
    ["report", "-"],
    ["run", C],
]


def typers_report(args: list[str], monkeypatch: pytest.MonkeyPatch) -> tuple[int, dict | None]:
    """(exit code, the arguments typer's `report` command passed on) for ``args``; nothing is read."""
    import orchestrator.cli.trace as trace_module

    built: list[dict] = []
    monkeypatch.setattr(trace_module, "report_command",
                        lambda trace, as_json, plots, overwrite: built.append(
                            {"trace": trace, "as_json": as_json, "plots": plots, "overwrite": overwrite}))
    result = CliRunner().invoke(app, args, env={"COLUMNS": "100", "NO_COLOR": "1", "TERM": "dumb"})
    return result.exit_code, (built[0] if built else None)


@pytest.mark.parametrize("args", REPORT_LINES, ids=lambda args: " ".join(args) or "(empty)")
def test_the_fast_start_reads_a_report_as_typer_does_or_leaves_it_to_typer(
        args: list[str], monkeypatch: pytest.MonkeyPatch) -> None:
    ours = plain_report_options(args)
    if ours is not None:  # taken without typer: exactly what typer's command would have run
        assert typers_report(args, monkeypatch) == (0, ours)


def test_the_plain_report_lines_above_are_taken_by_the_fast_start() -> None:
    plain = REPORT_LINES[:REPORT_LINES.index(["report"])]
    assert [args for args in REPORT_LINES if plain_report_options(args) is not None] == plain


def test_the_fast_start_knows_every_option_of_the_report_command_as_declared() -> None:
    command = typer.main.get_command(app).commands["report"]  # type: ignore[attr-defined]
    kinds = {Path: "path", bool: "flag"}
    declared = {name: (param.name, kinds[param.type_descriptor.annotation])
                for param in command.params if param.param_type_name != "argument" for name in param.opts}
    assert declared == REPORT_OPTIONS
    assert [param.name for param in command.params if param.param_type_name == "argument"] == ["trace"]
    assert all(param.min is None and param.max is None for param in command.params if hasattr(param, "min"))
