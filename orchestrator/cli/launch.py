"""The ``platoon`` console entry point: a plain `platoon run` or `platoon report` starts without typer;
everything else goes through the typer app (orchestrator/cli/app.py).

Loading typer, rich and every command group costs a run ~0.1 s before its first step, and a sweep is
made of short runs (docs/performance.md, "Start-up"). So a `platoon run` command line that is plainly
well formed (known options, each value where it belongs and in range, one config) is parsed here
into the same ``RunOptions`` the typer command builds, and run without typer. Anything else (help,
an unknown or repeated option, a value typer would refuse or read differently, shell completion)
goes to typer, which then answers exactly as before: its help, its error messages, its parsing.
tests/test_launch.py holds this parser to typer's on the command lines it accepts.

`platoon report TRACE` is read the same way (``REPORT_OPTIONS``): typer's parameter adapters and the other
commands' modules were a third of a report (orchestrator/cli/reporting.py).
"""

from __future__ import annotations

import os
import re
import sys
from pathlib import Path
from typing import Any

from orchestrator.cli import help_cache
from orchestrator.cli.options import RunOptions
from orchestrator.cli.process import run_and_exit

# `platoon run`'s options (orchestrator/cli/run.py): option -> (RunOptions field, kind of value)
RUN_OPTIONS: dict[str, tuple[str, str]] = {
    "--out": ("trace", "path"),
    "--set": ("overrides", "list"),
    "--monolithic": ("monolithic", "flag"),
    "--compare-monolithic": ("compare", "flag"),
    "--quiet": ("quiet", "flag"),
    "-q": ("quiet", "flag"),
    "--trace-every": ("trace_every", "int"),
    "--engine": ("engine_name", "text"),
    "--fmus": ("fmu_kind", "text"),
    "--trace-writer": ("trace_writer", "text"),
    "--overwrite": ("overwrite", "flag"),
    "--verbose": ("verbose", "flag"),
    "-v": ("verbose", "flag"),
    "--allow-long": ("allow_long", "flag"),
    "--live": ("live", "flag"),
    "--live-port": ("live_port", "int"),
    "--live-host": ("live_host", "text"),
    "--live-speed": ("live_speed", "float"),
    "--live-wait": ("live_wait", "flag"),
}
# `platoon report`'s options (orchestrator/cli/trace.py): option -> (report_command's argument, kind of value)
REPORT_OPTIONS: dict[str, tuple[str, str]] = {
    "--json": ("as_json", "flag"),
    "--plots": ("plots", "path"),
    "--overwrite": ("overwrite", "flag"),
}
# the ranges typer checks (min=, max= in run.py); a value outside goes to typer for its message
RUN_RANGES: dict[str, tuple[float | None, float | None]] = {
    "trace_every": (1, None), "live_port": (0, 65535), "live_speed": (0.0, None)}
_INTEGER = re.compile(r"[0-9]+")
_DECIMAL = re.compile(r"[0-9]+(\.[0-9]*)?|\.[0-9]+")


def main() -> None:
    """`platoon ARGS`: a plain `platoon run` without typer, anything else with it.

    Every command asks numpy's OpenBLAS for one thread first (unless the user chose a number): the
    analysis works on small matrices, where OpenBLAS's threads only spin, and `stability-map` runs a
    process per CPU already. With a thread per core in each of its two processes, the study's map
    took 5.6-6.3 s and 10.5 s of CPU; with one, 3.7 s and 5.4 s."""
    from orchestrator.support.startup import single_threaded_blas

    single_threaded_blas()
    args = sys.argv[1:]
    if args == ["--version"]:
        _print_version()
    if help_cache.is_help_request(args):  # shown again from the cache when nothing it depends on changed
        help_cache.replay(args)
        from orchestrator.cli.app import app

        run_and_exit(help_cache.recording(app, args))
    options = plain_run_options(args)
    report = plain_report_options(args) if options is None else None
    if report is not None:
        from orchestrator.cli.reporting import report_command

        run_and_exit(lambda: report_command(**report), without_typer=True)
    if options is None:
        from orchestrator.cli.app import main as typer_main

        typer_main()
        return
    from orchestrator.cli.trace_forecast import wants_trace_worker
    from orchestrator.support.startup import loading_a_run

    if wants_trace_worker(options):  # its start-up overlaps ours (pydantic, the models, the FMUs)
        from orchestrator.trace.worker import prestart

        prestart()
    with loading_a_run():  # without garbage collection (~2 % of a start-up); pydantic and the config models
        import orchestrator.cli.running  # noqa: F401  (load likewise when a config is not in the cache, plain.py)

    run_and_exit(lambda: _run(options), without_typer=True)


def _print_version() -> None:
    """`platoon --version` without typer and rich, when the line fits the terminal as rich measures it
    (else rich would wrap it: typer's option prints it then, orchestrator/cli/app.py)."""
    from orchestrator.cli.plain import say
    from orchestrator.support.versions import version_line

    line = version_line()
    widths = [int(os.environ["COLUMNS"])] if os.environ.get("COLUMNS", "").isdigit() else []
    for descriptor in (0, 1, 2):
        try:
            widths.append(os.get_terminal_size(descriptor).columns)
        except OSError:
            pass
    if len(line) < min(widths or [80], default=80):
        run_and_exit(lambda: say(line), without_typer=True)


def _run(options: RunOptions) -> None:
    from orchestrator.cli.running import run_command

    try:
        run_command(options)
    finally:
        from orchestrator.trace.worker import discard_prestarted

        discard_prestarted()  # a worker the run did not want (a wrong forecast, a refused config)


def plain_run_options(args: list[str]) -> RunOptions | None:
    """``RunOptions`` of a plainly well-formed `platoon run` command line, as typer would parse it; None
    for anything else (typer then handles it)."""
    values = _plain_command(args, "run", "config", RUN_OPTIONS)
    return None if values is None else RunOptions(**values)


def plain_report_options(args: list[str]) -> dict[str, Any] | None:
    """``report_command``'s arguments of a plainly well-formed `platoon report` command line, as typer would
    parse it (its defaults filled in); None for anything else (typer then handles it)."""
    values = _plain_command(args, "report", "trace", REPORT_OPTIONS)
    return None if values is None else {"as_json": False, "plots": None, "overwrite": False, **values}


def _plain_command(args: list[str], command: str, argument: str,
                   table: dict[str, tuple[str, str]]) -> dict[str, Any] | None:
    """The values of `platoon COMMAND`'s one ``argument`` and its options (``table``), read as typer reads a
    plainly well-formed command line; None for anything else."""
    if not args or args[0] != command or any(name.startswith("_") and name.endswith("_COMPLETE") for name in os.environ):
        return None  # not this command, or a shell's completion request
    values: dict[str, Any] = {}
    rest = args[1:]
    while rest:
        token, rest = rest[0], rest[1:]
        if not token.startswith("-"):
            if argument in values or not token:
                return None  # a second argument (typer: "Got unexpected extra argument"), or an empty one
            values[argument] = Path(token)
            continue
        name, equals, attached = token.partition("=")
        if name not in table:
            return None  # help, "--", "-qv", an unknown option ...
        field, kind = table[name]
        if kind == "flag":
            if equals:
                return None
            values[field] = True
            continue
        if not equals:
            if not rest:
                return None
            attached, rest = rest[0], rest[1:]
        value = _value(attached, kind, RUN_RANGES.get(field, (None, None)))
        if value is None or (kind != "list" and field in values):
            return None  # a value typer would refuse or read otherwise, or one option given twice
        values[field] = [*values.get(field, []), value] if kind == "list" else value
    return values if argument in values else None


def _value(text: str, kind: str, bounds: tuple[float | None, float | None]) -> Any:
    """The value of an option as typer reads it, or None where it might read it otherwise or refuse it."""
    if not text or text.startswith("-"):
        return None
    if kind in ("text", "list"):
        return text
    if kind == "path":
        return Path(text)
    if not (_INTEGER if kind == "int" else _DECIMAL).fullmatch(text):
        return None
    number = int(text) if kind == "int" else float(text)
    low, high = bounds
    if (low is not None and number < low) or (high is not None and number > high):
        return None
    return number
