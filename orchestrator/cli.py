"""The ``platoon`` command: build, run, report, export, trace recover, analyze, bench.

Exit codes: 0 success; 1 a run failed (the trace up to the failure is kept), or a trace held nothing
recoverable; 2 bad input (config, option or file), with one line naming what is wrong and no
traceback; 130 a run stopped by SIGINT (Ctrl-C) and 143 by SIGTERM (128 + the signal number, as a
shell reports a process killed by it), its trace finalized up to the stop.
"""

from __future__ import annotations

import json
import os
import sys
import warnings
from contextlib import contextmanager
from pathlib import Path
from typing import TYPE_CHECKING, Annotated, Iterator, Optional

import typer
from rich.console import Console
from rich.markup import escape

from .bench import ENGINES as BENCH_ENGINES
from .config import Config, ConfigError, parse_config, read_config_text

if TYPE_CHECKING:  # rich's progress bar and table are imported where used: `platoon run -q` needs neither
    from rich.table import Table

app = typer.Typer(
    add_completion=False,
    no_args_is_help=True,
    help="Platoon co-simulation: trajectory-shaping guidance FMUs, config-driven runs, MCAP traces.",
)
# No rich markup in what we print: names, paths and config text are the user's ("[[disturbance]]",
# "runs/[a]/x.mcap") and must appear as written. The one styled line (_fail) asks for markup itself.
out = Console(markup=False)
err = Console(stderr=True, markup=False)
# Metavars that show what an option takes (typer would print <str> or <list[str]>)
SET_METAVAR = "KEY=VALUE"
RUN_ENGINES = ("native", "python")  # --engine; --monolithic picks the third engine (run.ENGINES)


def choices_metavar(choices: tuple[str, ...]) -> str:
    """``<a|b|c>``: the allowed values of an option, as typer shows a choice type, for an option we check
    ourselves (so a wrong value is our one-line error, not typer's framed box)."""
    return "<" + "|".join(choices) + ">"


AllowLong = Annotated[bool, typer.Option("--allow-long", help="run even above the size limits (docs/config.md: more than "
                                         "1e6 steps, 1000 substeps per step or 1e8 FMU-substeps)")]


def _print_version(value: bool) -> None:
    if value:
        from .run import tool_versions

        versions = tool_versions()
        out.print(f"platoon {versions.pop('platoon-cosim')} ("
                  + ", ".join(f"{name} {version}" for name, version in versions.items()) + ")", highlight=False)
        raise typer.Exit()


@app.callback()
def _options(
    version: Annotated[bool, typer.Option("--version", callback=_print_version, is_eager=True,
                                          help="print the version (and of the FMUs, FMPy, pythonfmu, Python) and exit")] = False,
) -> None:
    """Platoon co-simulation: trajectory-shaping guidance FMUs, config-driven runs, MCAP traces."""


def _fail(code: int, message: str) -> None:
    err.print(f"[bold red]error:[/] {escape(message)}", markup=True, highlight=False, soft_wrap=True)
    raise typer.Exit(code)


def _load(config: Path, overrides: list[str], allow_long: bool = True) -> tuple[Config, str]:
    """The validated config and its text as read (stored in the trace); exit 2 naming the problem.
    ``allow_long=False`` also refuses a run above the size limits (orchestrator/limits.py)."""
    from .limits import check_run_size

    try:
        text = read_config_text(config)
        parsed, _ = parse_config(text, config.stem, overrides)
        if not allow_long:
            check_run_size(parsed)
    except ConfigError as error:
        _fail(2, f"config {config}: {error}")
    from .config_warnings import config_warnings

    for warning in config_warnings(parsed):  # valid, but probably not what was meant: the run still goes
        err.print(f"warning: config {config}: {warning}", highlight=False, soft_wrap=True)
    return parsed, text


@app.command()
def build(
    out_dir: Annotated[Path, typer.Option("--out", help="folder for Vehicle.fmu, VirtualTarget.fmu and LiveVehicle.fmu")] = Path("build/fmus"),
    force: Annotated[bool, typer.Option(help="rebuild even if up to date")] = False,
) -> None:
    """Build the Vehicle, VirtualTarget and LiveVehicle FMUs, and the native Vehicle and VirtualTarget into OUT/native (FMI 2.0) and OUT/fmi3 (FMI 3.0) (only when their sources changed)."""
    from fmus.build import ALL_FMUS, build_fmus

    try:
        built_fmus = build_fmus(out_dir, force=force, names=ALL_FMUS)
    except OSError as error:  # a full disk, a read-only folder ...: the FMUs already in place are untouched
        where = f" {error.filename}" if error.filename else ""
        _fail(2, f"build --out {out_dir}: cannot write the FMUs{where}: {error.strerror or error}")
    for built in built_fmus:
        state = "built" if built.rebuilt else "up to date"
        out.print(f"{built.path}  {built.guid}  ({state})", soft_wrap=True)
    _build_native(out_dir, force)


def _build_native(out_dir: Path, force: bool) -> None:
    """The native twins into OUT/native (fmus/native_build.py) and, as FMI 3.0 FMUs, into OUT/fmi3
    (fmus/native_build3.py); no compiler is one line, not a failure."""
    from fmus.build import BuildError
    from fmus.native_build import NoCompiler, build_native_fmus
    from fmus.native_build3 import build_fmi3_fmus

    try:
        built_fmus = build_native_fmus(out_dir / "native", force=force)
        built_fmus += build_fmi3_fmus(out_dir / "fmi3", force=force)
    except NoCompiler as error:
        err.print(f"note: {error}", soft_wrap=True)
        return
    except BuildError as error:
        _fail(2, f"build: {error}")
    except OSError as error:
        where = f" {error.filename}" if error.filename else ""
        _fail(2, f"build --out {out_dir}: cannot write the native FMUs{where}: {error.strerror or error}")
    for built in built_fmus:
        state = "built" if built.rebuilt else "up to date"
        out.print(f"{built.path}  {built.guid}  ({state}, native{' FMI 3.0' if built.path.parent.name == 'fmi3' else ''})", soft_wrap=True)


def _summary_table(summaries, config: Config, title: str) -> Table:
    """The per-vehicle summary (the consoles print text literally: the units "[m]" are not markup); the same
    quantities, keys and units as `platoon report --json` (metrics.SUMMARY_COLUMNS, summary_rows)."""
    from rich.table import Table

    from .metrics import STEADY_FRACTION, SUMMARY_COLUMNS, path_error_interval, summary_rows

    _, interval = path_error_interval(config)  # max |path error| is taken from the first disturbance on (metrics.py)
    table = Table(title=title, title_justify="left", caption_justify="left",
                  caption=f"path offset, gap, speed: means over the last {STEADY_FRACTION:.0%} of the recorded time")
    table.add_column("vehicle", justify="left")
    for column in SUMMARY_COLUMNS:
        header = f"{column.label} [{column.unit}]" + (f", {interval}" if column.key == "path_error_max" else "")
        table.add_column(header, justify="right",
                         min_width=len(column.label) if column.key == "path_error_max" else None,  # unbroken
                         max_width=len("path offset") if column.key == "path_offset" else None)  # fits 80 columns
    for row in summary_rows(summaries, config):  # deviations signed; the largest |error| is a magnitude
        table.add_row(str(row["name"]), *(f"{row[c.key]:.3e}" if c.key == "path_error_max" else f"{row[c.key]:+.3e}"
                                           for c in SUMMARY_COLUMNS))
    return table


def _time_split(entered: float | None, loaded: float | None, imported: float | None, timings: dict[str, float],
                now: float | None) -> str:
    """``-v``: where this process's wall time went, from the interpreter's start to now (a few lines)."""
    def seconds(value: float | None) -> str:
        return "?" if value is None else f"{value:.2f} s"

    def between(start: float | None, end: float | None) -> float | None:
        return None if start is None or end is None else end - start

    run_total = sum(timings.values())
    rest = None if now is None or imported is None else max(0.0, now - imported - run_total)  # clock reads a few µs apart: never "-0.00 s"
    phases = ", ".join(f"{name} {timings[name]:.2f} s" for name in ("setup", "initialize", "steps", "finish")
                       if name in timings)
    return "\n".join([
        f"wall time since the process started: {seconds(now)}",
        f"  start-up: interpreter and imports {seconds(entered)}, config {seconds(between(entered, loaded))},",
        f"            run modules imported {seconds(between(loaded, imported))}, "
        f"FMUs checked and unpacked {seconds(timings.get('open'))}",
        f"  run: {phases}",
        f"  after the run (summary, output): {seconds(rest)}",
    ])


def _execute(config: Config, text: str, trace, engine: str, quiet: bool, trace_writer: str = "auto", live_view=None):
    from .progress import progress
    from .run import run_scenario
    from .scenario import step_count

    steps = step_count(config.simulation.stop_time, config.simulation.step)
    with progress(steps, "simulating", err, quiet) as tick:  # a bar on a terminal, plain lines in a pipe or a log
        return run_scenario(config, text, trace, engine=engine, tick=tick, trace_writer=trace_writer, summarize=not quiet,
                            live_view=live_view)


OVERWRITE_HELP = "replace an existing --out even if it is not an MCAP trace (never the command's own input)"


def _check_output(path: Path, overwrite: bool, protect: list[Path], what: str = "--out") -> None:
    """Exit 2 with one line if ``path`` must not be replaced (trace/output.py: check_replaceable)."""
    from .trace.output import OutputError, check_replaceable

    try:
        check_replaceable(path, overwrite, protect, what)
    except OutputError as error:
        _fail(2, str(error))


def _claim_trace(trace: Optional[Path], overwrite: bool, protect: list[Path], default):
    """Claim the trace path before any work (orchestrator/trace/output.py): exit 2 with one line if it is
    in use by another run, is a file that is not a trace (without --overwrite), is the config, or cannot
    be written."""
    from .trace.output import OutputError, claim

    try:
        return claim(trace, overwrite, protect) if trace is not None else default()
    except OutputError as error:
        _fail(2, str(error))


@app.command()
def run(
    config: Annotated[Path, typer.Argument(help="scenario TOML file, e.g. configs/paper/platoon.toml")],
    trace: Annotated[Optional[Path], typer.Option("--out", help="trace file (default runs/<name>-<time>.mcap)")] = None,
    overrides: Annotated[list[str], typer.Option("--set", metavar=SET_METAVAR, help="override a key, e.g. --set platoon.law=regular")] = [],
    monolithic: Annotated[bool, typer.Option("--monolithic", help="integrate the whole platoon as one system (reference)")] = False,
    compare: Annotated[bool, typer.Option("--compare-monolithic", help="also run the monolithic reference and print the largest deviations")] = False,
    quiet: Annotated[bool, typer.Option("--quiet", "-q", help="no progress bar and no table")] = False,
    trace_every: Annotated[Optional[int], typer.Option("--trace-every", min=1, help="record every K-th communication point (overrides simulation.trace_every)")] = None,
    engine_name: Annotated[Optional[str], typer.Option("--engine", metavar=choices_metavar(RUN_ENGINES), help="native (compiled stepping core; default when built) or python (FMPy); same results")] = None,
    fmu_kind: Annotated[Optional[str], typer.Option("--fmus", metavar=choices_metavar(("native", "python")), help="native (C FMUs, default where a C compiler can build them) or python (pythonfmu FMUs); same results (overrides simulation.fmus)")] = None,
    trace_writer: Annotated[str, typer.Option("--trace-writer", metavar=choices_metavar(("auto", "inline", "process")), help="where the trace is encoded: process (a second process), inline, or auto (a second process for long runs on a multi-core machine); same file")] = "auto",
    overwrite: Annotated[bool, typer.Option("--overwrite", help=OVERWRITE_HELP)] = False,
    verbose: Annotated[bool, typer.Option("--verbose", "-v", help="also print where the wall time went: start-up (imports, config, FMUs), the run's phases, the summary")] = False,
    allow_long: AllowLong = False,
    live: Annotated[bool, typer.Option("--live", help="serve the run on a Foxglove WebSocket while it runs (open it in Foxglove or Lichtblick; docs/foxglove.md), paced to real time")] = False,
    live_port: Annotated[int, typer.Option("--live-port", min=0, max=65535, help="port of the --live server")] = 8765,
    live_host: Annotated[str, typer.Option("--live-host", metavar="ADDRESS", help="address the --live server binds; anything but 127.0.0.1 lets other machines watch (no authentication)")] = "127.0.0.1",
    live_speed: Annotated[float, typer.Option("--live-speed", min=0.0, help="with --live: simulated seconds per wall second (1: real time; 0: as fast as it runs)")] = 1.0,
    live_wait: Annotated[bool, typer.Option("--live-wait", help="with --live: start stepping once a viewer shows the scene, so it sees the whole run")] = False,
) -> None:
    """Run a scenario: wire the FMUs as the paper's Fig. 2, step them, write an MCAP trace."""
    from .startup import loading_a_run, seconds_since_process_start

    entered = seconds_since_process_start()  # the interpreter and the imports so far
    if trace_every is not None:
        overrides = [*overrides, f"simulation.trace_every={trace_every}"]
    if fmu_kind is not None:
        overrides = [*overrides, f"simulation.fmus={json.dumps(fmu_kind)}"]
    parsed, text = _load(config, overrides, allow_long)
    loaded = seconds_since_process_start()
    with loading_a_run():  # one BLAS thread, no garbage collection while the run's modules load
        from .run import default_engine, default_trace_path

    imported = seconds_since_process_start()  # the engines, numpy, the trace writer
    if engine_name is not None and engine_name not in RUN_ENGINES:
        _fail(2, f"--engine {engine_name!r}: expected native or python")
    if engine_name == "native" and default_engine() != "native":
        _fail(2, "--engine native: the compiled core is not built here (reinstall with a C compiler: pip install -e .)")
    from .live import LiveRunError, check_live_options
    from .run import TRACE_WRITERS

    if trace_writer not in TRACE_WRITERS:
        _fail(2, f"--trace-writer {trace_writer!r}: expected one of {', '.join(TRACE_WRITERS)}")
    engine = "monolithic" if monolithic else (engine_name or default_engine(parsed))
    try:
        check_live_options(parsed, engine, trace_writer)
    except LiveRunError as error:
        _fail(2, f"config {config}: {error}")
    view = None
    if not live and (live_port, live_host, live_speed, live_wait) != (8765, "127.0.0.1", 1.0, False):
        _fail(2, "--live-port, --live-host, --live-speed and --live-wait go with --live (add it to watch the run)")
    if live:  # before the trace is claimed: a port in use stops the run with nothing written
        from .live_view import LiveViewError, start_live_view

        try:
            view = start_live_view(parsed, live_host, live_port, live_speed, err, live_wait)
        except LiveViewError as error:
            _fail(2, str(error))
    target = _claim_trace(trace, overwrite, [config], lambda: default_trace_path(parsed, engine))
    trace = target.final
    reference_path = trace.with_name(trace.stem + "-monolithic.mcap")
    if compare:  # checked now, claimed when its turn comes (no empty aside file if the run fails)
        _check_output(reference_path, overwrite, [config])
    from fmus.build import BuildError

    from .fmu_kinds import FmuKindError

    if view is not None:
        from .live_view import announce

        announce(view, trace, parsed, out)
    try:
        result = _execute(parsed, text, target, engine, quiet, trace_writer, view)
    except (FmuKindError, BuildError) as error:  # nothing was run, the trace path is released
        _fail(2, f"config {config}: {error}")
    finally:
        if view is not None:
            view.close()
            if (lag := view.lag_note()) is not None:
                err.print(lag, highlight=False, soft_wrap=True)
    from .viewer_cli import write_run_layout

    layout = write_run_layout(trace, parsed, warn=result.status == "completed")  # beside the trace; None: not written
    if result.live:
        from .hil_cli import live_table

        out.print(live_table(result.live))
    if result.status == "interrupted":
        _fail(128 + (result.signal or 2), f"run {result.status}: {result.error} (trace up to that point: {result.trace})")
    if result.status != "completed":
        _fail(1, f"run {result.status}: {result.error} (trace up to that point: {result.trace})")
    if not quiet:
        from .metrics import summarize
        from .trace import load

        # accumulated while stepping; the trace is read again only if the run's end was not the planned one
        summaries = result.summary if result.summary is not None else summarize(load(result.trace), parsed)
        out.print(_summary_table(summaries, parsed, f"{parsed.name}: {parsed.platoon.law} law, {engine} engine, {result.fmus} FMUs, {parsed.simulation.stop_time:g} s"))
    out.print(f"trace: {result.trace}  ({result.steps} steps in {result.wall_time:.2f} s)", highlight=False, soft_wrap=True)
    if layout is not None:
        out.print(f"layout: {layout}  (open both in Foxglove: docs/foxglove.md)", highlight=False, soft_wrap=True)  # one line in a log
    if verbose:
        err.print(_time_split(entered, loaded, imported, result.timings, seconds_since_process_start()), highlight=False)
    if compare:
        from .compare import deviations
        from .trace import load

        reference = _execute(parsed, text, _claim_trace(reference_path, overwrite, [config], None), "monolithic", quiet)
        if reference.status != "completed":
            _fail(1, f"monolithic reference {reference.status}: {reference.error}")
        worst = deviations(load(result.trace), load(reference.trace))
        out.print(
            f"largest deviation from the monolithic run ({reference.trace}): "
            f"position {worst.position:.3e} m ({worst.position_where}), gap {worst.gap:.3e} m, speed {worst.speed:.3e} m/s"
        )


@app.command()
def report(
    trace: Annotated[Path, typer.Argument(help="trace written by `platoon run`")],
    as_json: Annotated[bool, typer.Option("--json", help="print the summary as JSON")] = False,
    plots: Annotated[Optional[Path], typer.Option("--plots", help="write the paper's figure panels as PNG here")] = None,
) -> None:
    """Summarize a trace (path offset, gap, speed, max path error) and draw the paper's panels."""
    from .metrics import report_json, summarize
    from .stored_config import stored_config

    if plots is not None and plots.exists() and not plots.is_dir():
        _fail(2, f"--plots {plots}: is a file; give a folder for the PNG files")
    loaded = _load_trace(trace)
    if loaded.config is None:
        _fail(2, f"trace {trace}: has no platoon.config metadata (not written by platoon run?)")
    try:
        config, non_finite = stored_config(loaded.config)
    except ConfigError as error:
        _fail(2, f"trace {trace}: its stored config is not valid: {error}")
    note = (err.print if as_json else out.print)
    if non_finite:
        note(f"warning: the run's config held values that were not finite (stored as null): {', '.join(non_finite)}; "
             f"figures that depend on them are nan", highlight=False, soft_wrap=True)
    _note_recovery(loaded, note)
    run_record = loaded.run
    status = run_record.get("status", "?")
    empty = not loaded.vehicles() or any(len(loaded.component(v)["t"]) == 0 for v in loaded.vehicles())
    if empty:  # e.g. a run that failed before its first communication point: nothing to summarize or plot
        reason = f": {run_record['error']}" if run_record.get("error") else ""
        message = f"trace {trace}: no recorded communication point, nothing to summarize (run {status}{reason})"
        if as_json:
            out.print_json(json.dumps({"status": status, "error": run_record.get("error", ""), "vehicles": []}))
            err.print(message, highlight=False, soft_wrap=True)
        else:
            out.print(message, highlight=False, soft_wrap=True)
        return
    with _quiet_nan(bool(non_finite)):  # nan figures were announced above
        summaries = summarize(loaded, config)
        if as_json:
            out.print_json(json.dumps({"trace": str(trace), "law": config.platoon.law, "status": status,
                                        **report_json(summaries, config)}))
        else:
            out.print(_summary_table(summaries, config, f"{trace.name}: {config.platoon.law} law ({status})"))
        if plots is not None:
            from .plots import write_plots

            try:
                written = write_plots(loaded, config, plots)
            except OSError as error:
                _fail(2, f"--plots {plots}: cannot write the plots there: {error.strerror or error}")
            for path in written:
                note(f"wrote {path}")


@contextmanager
def _quiet_nan(quiet: bool) -> Iterator[None]:
    """Silence numpy's invalid-value warnings when a config's non-finite values make figures nan on purpose."""
    if not quiet:
        yield
        return
    import numpy as np

    with np.errstate(all="ignore"), warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        yield


def _note_recovery(loaded, note) -> None:
    """A trace written by `platoon trace recover` with damaged stretches skipped: say which time is missing."""
    record = loaded.metadata.get("platoon.recovery")
    if not record or record.get("damaged", "0") == "0":
        return
    from .trace.recovery import describe_lost

    lost = [tuple(pair) for pair in json.loads(record.get("lost", "[]"))]
    note(f"warning: recovered from a damaged trace; data is missing between {describe_lost(lost)}",
         highlight=False, soft_wrap=True)


def _load_trace(trace: Path):
    from .trace import TraceError, load

    if not trace.is_file():
        _fail(2, f"trace {trace}: no such file")
    try:
        return load(trace)
    except TraceError as error:  # says what is wrong and what to do (e.g. `platoon trace recover`)
        _fail(2, f"trace {trace}: not a readable MCAP trace: {error}")
    except Exception as error:  # any other reader failure means the file is not a usable trace
        _fail(2, f"trace {trace}: not a readable MCAP trace ({error}); try `platoon trace recover {trace}`")


@app.command()
def export(
    trace: Annotated[Path, typer.Argument(help="trace written by `platoon run`")],
    csv_dir: Annotated[Path, typer.Option("--csv", help="folder for one CSV per component (header: t, then the outputs)")],
) -> None:
    """Export a trace: one CSV per component (t, then its outputs) and errors.csv (path, gap, speed errors)."""
    from .trace import export_csv

    if csv_dir.exists() and not csv_dir.is_dir():
        _fail(2, f"--csv {csv_dir}: is a file; give a folder for the CSV files")
    loaded = _load_trace(trace)
    _note_recovery(loaded, err.print)
    try:
        written = export_csv(loaded, csv_dir)
    except OSError as error:
        _fail(2, f"--csv {csv_dir}: cannot write the CSV files there: {error.strerror or error}")
    for path in written:
        out.print(f"wrote {path}", highlight=False, soft_wrap=True)


trace_app = typer.Typer(no_args_is_help=True, help="Work on trace files.")
app.add_typer(trace_app, name="trace")


@trace_app.command("recover")
def trace_recover(
    broken: Annotated[Path, typer.Argument(help="an unfinished or damaged trace (e.g. the run was killed)")],
    fixed: Annotated[Optional[Path], typer.Option("--out", help="recovered trace (default BROKEN-recovered.mcap)")] = None,
    overwrite: Annotated[bool, typer.Option("--overwrite", help="replace an existing --out (never BROKEN itself)")] = False,
) -> None:
    """Rewrite the intact chunks of an unfinished or damaged trace into a valid one; say what was lost."""
    from .trace import TraceError, recover
    from .trace.output import OutputError, check_in_use, claim, publish
    from .trace.recovery import describe_lost

    if not broken.is_file():
        _fail(2, f"trace {broken}: no such file")
    if fixed is None:
        name = broken.name[:-len(".partial")] if broken.name.endswith(".mcap.partial") else broken.name
        fixed = broken.with_name(Path(name).stem + "-recovered.mcap")
    try:
        check_in_use(broken)
        if fixed.exists() and not overwrite and not _same(fixed, broken):
            raise OutputError(f"--out {fixed}: exists; pass --overwrite to replace it")
        target = claim(fixed, overwrite=True, protect=[broken], suffix=".recovering")
    except OutputError as error:
        _fail(2, str(error))
    try:
        result = recover(broken, target.aside)
        publish(target.aside, target.final)
    except (TraceError, OSError) as error:
        target.aside.unlink(missing_ok=True)  # no half-written file left behind
        target.release()
        if isinstance(error, TraceError):
            _fail(2, str(error))
        _fail(2, f"--out {fixed}: cannot write the recovered trace: {error.strerror or error} (nothing written)")
    target.release()
    stretches = "stretch" if result.damaged == 1 else "stretches"
    damage = f"; {result.damaged} damaged {stretches} skipped, data lost between {describe_lost(result.lost)}" if result.damaged else ""
    if result.steps == 0:
        _fail(1, f"trace {broken}: no complete communication point to recover ({result.chunks} intact chunks{damage}); "
                 f"wrote {fixed} with its metadata only")
    span = f"t = 0 .. {result.last_time:.6g} s" if result.last_time is not None else "no time"
    state = "a complete file" if result.finished else f"{result.chunks} intact chunks"
    out.print(f"recovered {result.steps} communication points ({span}, {result.messages} messages) from {state}: {fixed}"
              f"{damage}", highlight=False, soft_wrap=True)


def _same(a: Path, b: Path) -> bool:
    try:
        return os.path.samefile(a, b)
    except OSError:
        return False


@app.command()
def analyze(
    config: Annotated[Path, typer.Argument(help="scenario TOML file")],
    overrides: Annotated[list[str], typer.Option("--set", metavar=SET_METAVAR, help="override a key, as for platoon run")] = [],
    string_stability: Annotated[bool, typer.Option(help="also run the scenario and report peak-error ratios")] = True,
    allow_long: AllowLong = False,
) -> None:
    """Linearize about the circular equilibrium; eigenvalues next to the paper's eq. 9; string stability."""
    from .analysis import eigen_report, string_stability_report
    from .limits import check_analyze_size, check_run_size

    parsed, text = _load(config, overrides)
    if not allow_long:
        try:
            check_analyze_size(parsed)
            if string_stability and parsed.disturbance:  # only then is the scenario run (twice)
                check_run_size(parsed)
        except ConfigError as error:
            _fail(2, f"config {config}: {error}")
    try:
        report_text = eigen_report(parsed)
    except ValueError as error:
        _fail(2, f"config {config}: {error}")
    out.print(report_text, highlight=False, soft_wrap=True)
    if string_stability:
        from .progress import progress

        shown = lambda label, total: progress(total, label, err)  # noqa: E731  (the runs: bar or plain lines)
        out.print(string_stability_report(parsed, text, shown), highlight=False, soft_wrap=True)


bench_app = typer.Typer(no_args_is_help=True, help="Benchmarks: what steps and whole runs cost against FMPy and libcosim, memory per vehicle, HIL latency (JSON under runs/bench/; not pass/fail tests; docs/performance.md).")
app.add_typer(bench_app, name="bench")

ROUNDS_HELP = "interleaved repetitions (each variant once per round, order rotated); medians over rounds"
OutDir = Annotated[Path, typer.Option("--out-dir", help="folder for the JSON results")]
Quiet = Annotated[bool, typer.Option("--quiet", "-q", help="no progress, only the tables and the result file")]
Engines = Annotated[str, typer.Option(metavar="ENGINE,...", help=f"comma-separated, of: {', '.join(BENCH_ENGINES)}")]
Counts = Annotated[str, typer.Option("--n", metavar="N,...", help="comma-separated vehicle counts")]
Steps = Annotated[int, typer.Option(min=1, help="communication steps of 0.01 s per measurement")]
Rounds = Annotated[int, typer.Option(min=1, help=ROUNDS_HELP)]


def _csv(option: str, text: str, choices: tuple[str, ...]) -> list[str]:
    """A comma-separated list of names out of ``choices``; anything else is a usage error (exit 2)."""
    names = [name.strip() for name in text.split(",") if name.strip()]
    unknown = [name for name in names if name not in choices]
    if not names or unknown:
        _fail(2, f"{option} {text!r}: expected a comma-separated list of {', '.join(choices)}")
    return list(dict.fromkeys(names))


def _counts(text: str) -> list[int]:
    """``--n``: comma-separated vehicle counts, each at least 1."""
    try:
        counts = [int(part) for part in text.split(",") if part.strip()]
    except ValueError:
        counts = []
    if not counts or min(counts) < 1:
        _fail(2, f"--n {text!r}: expected comma-separated vehicle counts of at least 1, e.g. 4,16,64,256")
    return list(dict.fromkeys(counts))


class _BenchProgress:
    """One line per measurement; on a terminal also a bar (stderr) counting the measurements done."""

    def __init__(self, quiet: bool) -> None:
        self.quiet = quiet
        self.bar: Progress | None = None
        self.task = None
        if not quiet and err.is_terminal:
            from rich.progress import BarColumn, Progress, TextColumn, TimeElapsedColumn, TimeRemainingColumn

            self.bar = Progress(TextColumn("[bold]measuring"), BarColumn(), TextColumn("{task.completed}/{task.total}"),
                                TimeElapsedColumn(), TimeRemainingColumn(), console=err, transient=True)

    def __enter__(self) -> "_BenchProgress":
        if self.bar is not None:
            self.bar.start()
        return self

    def __exit__(self, *exc: object) -> None:
        if self.bar is not None:
            self.bar.stop()

    def __call__(self, done: int, total: int, line: str) -> None:
        if self.quiet:
            return
        if self.bar is not None:
            if self.task is None:
                self.task = self.bar.add_task("measuring", total=total)
            self.bar.update(self.task, completed=done, total=total)
        err.print(line, highlight=False, soft_wrap=True)


def _bench(suite: str, measure, render, out_dir: Path, quiet: bool) -> None:
    """Run one suite with progress, print its tables, write its JSON; bad options exit 2, failures 1."""
    from .bench.common import BenchError, BenchUsageError, write_result

    try:
        with _BenchProgress(quiet) as progress:
            result = measure(progress)
    except BenchUsageError as error:
        _fail(2, str(error))
    except BenchError as error:
        _fail(1, f"bench {suite}: {error}")
    result["command"] = " ".join(["platoon", *sys.argv[1:]])
    out.print(render(result), highlight=False, soft_wrap=True)
    out.print(f"results: {write_result(out_dir, suite, result)}", highlight=False, soft_wrap=True)


def _per_fmu_step(suite_name: str, engines: str, n: str, steps: int, rounds: int, out_dir: Path, quiet: bool,
                  **options) -> None:
    """The two suites of FMU-step costs (``steps``, ``coupling``): same options, same checks."""
    from importlib import import_module

    suite = import_module(f".bench.{suite_name}", __package__)
    chosen, counts = _csv("--engines", engines, BENCH_ENGINES), _counts(n)
    _bench(suite_name, lambda progress: suite.run(chosen, counts, steps, rounds, progress=progress, **options),
           suite.markdown, out_dir, quiet)


@bench_app.command("steps")
def bench_steps(engines: Engines = "native,python,fmpy-bare,libcosim,libcosim-0threads,libcosim-0threads-lastvalue,slaves",
                n: Counts = "4,16,64,256", steps: Steps = 1000, rounds: Rounds = 5,
                out_dir: OutDir = Path("runs/bench"), quiet: Quiet = False,
                fmus: Annotated[Optional[str], typer.Option("--fmus", metavar="KIND,...", help="comma-separated FMU kinds: python, native (default: both where a C compiler builds the native ones)")] = None) -> None:
    """Microseconds per FMU-step of our engines, the bare FMPy loop, libcosim and the floor, by N, for the
    pythonfmu FMUs and the native ones."""
    from .fmu_kinds import FMU_KINDS

    kinds = None if fmus is None else _csv("--fmus", fmus, FMU_KINDS)
    _per_fmu_step("steps", engines, n, steps, rounds, out_dir, quiet, fmu_kinds=kinds)


@bench_app.command("coupling")
def bench_coupling(engines: Engines = "native,slaves", n: Counts = "4,16,64", steps: Steps = 1000, rounds: Rounds = 5,
                   out_dir: OutDir = Path("runs/bench"), quiet: Quiet = False) -> None:
    """Cost per FMU-step with coupling "hold" against "extrapolate" (same rounds, same engines)."""
    _per_fmu_step("coupling", engines, n, steps, rounds, out_dir, quiet)


@bench_app.command("scenarios")
def bench_scenarios(
    configs: Annotated[list[Path], typer.Option("--config", metavar="CONFIG", help="scenario TOML (repeatable; default configs/paper/*.toml)")] = [],
    engines: Annotated[str, typer.Option(metavar="ENGINE,...", help="comma-separated: native, python")] = "native,python",
    variants: Annotated[str, typer.Option(metavar="VARIANT,...", help="comma-separated: cli-traced (platoon run --out X -q), traced, untraced")] = "cli-traced,traced,untraced",
    rounds: Rounds = 3,
    overrides: Annotated[list[str], typer.Option("--set", metavar=SET_METAVAR, help="override a key in every scenario")] = [],
    out_dir: OutDir = Path("runs/bench"),
    quiet: Quiet = False,
) -> None:
    """Whole-run wall times of the paper's scenarios, start-up included, traced and untraced."""
    from .bench import scenarios as suite

    chosen = _csv("--engines", engines, suite.ENGINES)
    kinds = _csv("--variants", variants, suite.VARIANTS)
    _bench("scenarios", lambda progress: suite.run(configs or None, chosen, kinds, rounds, overrides, progress=progress),
           suite.markdown, out_dir, quiet)


@bench_app.command("wholerun")
def bench_wholerun(
    n: Counts = "16",
    steps: Steps = 10_000,
    variants: Annotated[str, typer.Option(metavar="VARIANT,...", help="comma-separated: platoon (default run, traced, table), platoon-q (-q --trace-every 100), libcosim (no observer), libcosim-outputs (time series of every output), libcosim-last-value")] = "platoon,platoon-q,libcosim,libcosim-outputs,libcosim-last-value",
    rounds: Rounds = 5,
    out_dir: OutDir = Path("runs/bench"),
    quiet: Quiet = False,
    fmus: Annotated[str, typer.Option("--fmus", metavar="<python|native>", help="the FMUs every variant steps: python (pythonfmu, the system the floors were set on) or native (the C twins)")] = "python",
) -> None:
    """Whole `platoon run` processes against libcosim running the same system from an SSP (0 threads)."""
    from .bench import wholerun as suite
    from .fmu_kinds import FMU_KINDS

    if fmus not in FMU_KINDS:
        _fail(2, f"--fmus {fmus!r}: expected one of {', '.join(FMU_KINDS)}")
    kinds, counts = _csv("--variants", variants, suite.VARIANTS), _counts(n)
    _bench("wholerun", lambda progress: suite.run(counts, steps, rounds, kinds, progress=progress, fmus=fmus),
           suite.markdown, out_dir, quiet)


@bench_app.command("instances")
def bench_instances(
    engines: Annotated[str, typer.Option(metavar="ENGINE,...", help="comma-separated: native, fmpy")] = "native,fmpy",
    n: Counts = "4,16,64,256",
    wirings: Annotated[str, typer.Option(metavar="WIRING,...", help="comma-separated: instances (unconnected), platoon (wired, settle sweeps)")] = "instances,platoon",
    rounds: Rounds = 3,
    out_dir: OutDir = Path("runs/bench"),
    quiet: Quiet = False,
) -> None:
    """Instantiation time and RSS per vehicle instance (slope over N), native engine and FMPy."""
    from .bench import instances as suite

    chosen, counts = _csv("--engines", engines, suite.ENGINES), _counts(n)
    kinds = _csv("--wirings", wirings, suite.WIRINGS)
    _bench("instances", lambda progress: suite.run(chosen, counts, rounds, kinds, progress=progress), suite.markdown,
           out_dir, quiet)


@bench_app.command("profile")
def bench_profile(
    n: Counts = "4,16,64",
    steps: Annotated[int, typer.Option(min=1, help="steps per sample (capped to 20 s simulated in all)")] = 1000,
    rounds: Rounds = 3,
    out_dir: OutDir = Path("runs/bench"),
    quiet: Quiet = False,
) -> None:
    """Where the native engine's time goes: native loop against the floor in one process, perf split."""
    from .bench import profile as suite

    counts = _counts(n)
    _bench("profile", lambda progress: suite.run(counts, steps, rounds, progress=progress), suite.markdown, out_dir, quiet)


@bench_app.command("flatness")
def bench_flatness(
    n: Counts = "4,16,64,256",
    steps: Annotated[int, typer.Option(min=1, help="steps per sample")] = 150,
    rounds: Annotated[int, typer.Option(min=1, help="interleaved samples per process")] = 5,
    repeats: Annotated[int, typer.Option(min=1, help="processes per N and experiment")] = 3,
    callgrind: Annotated[bool, typer.Option("--callgrind", help="also count instructions and simulated cache misses (valgrind; slow)")] = False,
    out_dir: OutDir = Path("runs/bench"),
    quiet: Quiet = False,
) -> None:
    """Why the cost per FMU-step grows with N: stepping order, idle instances, object sizes, cache misses."""
    from .bench import flatness as suite

    counts = _counts(n)
    _bench("flatness", lambda progress: suite.run_suite(counts, steps, rounds, repeats, callgrind, progress=progress),
           suite.suite_markdown, out_dir, quiet)


CORE_BUILD_HELP = "LABEL=PATH of a built orchestrator/native/_core .so (copy it aside before rebuilding _core.c)"


@bench_app.command("callgrind")
def bench_callgrind(
    n: Counts = "4,16,64,256",
    engines: Annotated[str, typer.Option(metavar="ENGINE,...", help="comma-separated: native, python, fmpy-bare")] = "native",
    fmu_steps: Annotated[int, typer.Option(min=1, help="FMU-steps per measurement (steps = this / (N + 1))")] = 2500,
    ll: Annotated[str, typer.Option("--ll", metavar="CACHE,...", help="comma-separated last-level caches to simulate: l2 (this machine's "
                                               "512 KiB L2), detected (valgrind's choice, the L3)")] = "l2",
    cores: Annotated[list[str], typer.Option("--core", metavar="LABEL=PATH", help=f"{CORE_BUILD_HELP}; repeatable (native engine; default: the installed core)")] = [],
    out_dir: OutDir = Path("runs/bench"),
    quiet: Quiet = False,
) -> None:
    """Instructions and cache misses per FMU-step of an engine's stepping (valgrind), the master's own apart."""
    from .bench import flatness as suite

    counts, chosen = _counts(n), _csv("--engines", engines, suite.CALLGRIND_ENGINES)
    levels = [suite.LAST_LEVELS[name] for name in _csv("--ll", ll, tuple(suite.LAST_LEVELS))]
    _bench("callgrind", lambda progress: suite.callgrind_series(counts, fmu_steps, levels, suite.core_builds(cores) or None,
                                                                progress=progress, engines=chosen),
           suite.callgrind_markdown, out_dir, quiet)


@bench_app.command("cores")
def bench_cores(
    builds: Annotated[list[str], typer.Argument(metavar="LABEL=PATH", help=f"{CORE_BUILD_HELP}; at least two", show_default=False)],
    n: Counts = "4,16,64,256",
    steps: Steps = 1000,
    rounds: Rounds = 5,
    out_dir: OutDir = Path("runs/bench"),
    quiet: Quiet = False,
) -> None:
    """The native engine with two or more builds of _core.c: µs per FMU-step, interleaved in fresh interpreters."""
    from .bench import flatness as suite

    counts = _counts(n)
    _bench("cores", lambda progress: suite.compare_cores(suite.core_builds(builds), counts, steps, rounds, progress=progress),
           suite.cores_markdown, out_dir, quiet)


from .hil_cli import register as _register_hil  # noqa: E402  (the m3pi-emulator and m3pi-serial commands)

_register_hil(app, bench_app)
from .sweep.cli import register as _register_sweep  # noqa: E402  (sweep, sweep-plot, bench sweep)

_register_sweep(app, bench_app)

from .ssp_cli import register as _register_ssp  # noqa: E402  (export-ssp: the platoon for other tools)

_register_ssp(app)
from .viewer_cli import register as _register_viewer  # noqa: E402  (layout, figure: what users look at)

_register_viewer(app)


def main() -> None:
    """Console entry point: run the command, then leave without interpreter teardown.

    pythonfmu FMUs embed themselves in the host's interpreter, and its teardown after they ran
    intermittently corrupts the heap (glibc aborts with "corrupted double-linked list", seen in
    roughly one run in five when started through the console script). Every file is closed and every
    line printed by the time a command returns, so we flush and exit with the command's code directly.
    """
    code = 0
    try:
        app()
    except SystemExit as done:
        code = done.code if isinstance(done.code, int) else (0 if done.code is None else 1)
        if isinstance(done.code, str):
            print(done.code, file=sys.stderr)
    except BaseException:  # an unexpected error: show it, as Python would, then exit 1
        import traceback

        traceback.print_exc()
        code = 1
    finally:
        sys.stdout.flush()
        sys.stderr.flush()
    os._exit(code)


if __name__ == "__main__":  # python -m orchestrator.cli ARGS: the platoon command
    main()


class _PlainFlags:
    """``--help`` without a ``<bool>`` after each flag: a flag takes no value, and a newcomer reading
    ``--quiet <bool>`` would type ``--quiet true``."""

    def get_params(self, ctx):  # type: ignore[no-untyped-def]
        params = super().get_params(ctx)  # type: ignore[misc]
        for param in params:
            if getattr(param, "is_flag", False) and param.metavar is None:
                param.metavar = " "  # shown instead of the type: nothing
        return params


class _PlainFlagsCommand(_PlainFlags, typer.core.TyperCommand):
    pass


class _PlainFlagsGroup(_PlainFlags, typer.core.TyperGroup):
    pass


def _plain_flags(typer_app: typer.Typer) -> None:
    """Every command and group of ``typer_app`` (and its sub-apps) shows its flags plainly."""
    def default(cls: object, base: type) -> bool:  # not chosen by whoever declared it: typer's default
        return cls is None or cls is base or isinstance(cls, typer.models.DefaultPlaceholder)

    if default(typer_app.info.cls, typer.core.TyperGroup):
        typer_app.info.cls = _PlainFlagsGroup
    for command in typer_app.registered_commands:
        if default(command.cls, typer.core.TyperCommand):
            command.cls = _PlainFlagsCommand
    for group in typer_app.registered_groups:
        if default(group.cls, typer.core.TyperGroup):
            group.cls = _PlainFlagsGroup
        if group.typer_instance is not None:
            _plain_flags(group.typer_instance)


_plain_flags(app)
