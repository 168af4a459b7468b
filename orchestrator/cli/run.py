"""`platoon build`, `platoon run` and `platoon analyze`: build the FMUs, run a scenario (with its progress,
summary, layout and optional monolithic comparison), linearize a config."""

from __future__ import annotations

import json
from pathlib import Path
from typing import TYPE_CHECKING, Annotated, Optional

import typer

from orchestrator.cli.common import (AllowLong, OVERWRITE_HELP, SET_METAVAR, check_choice, check_output, choices_metavar, claim_trace, err, fail,
                                     load_config, out, summary_table)
from orchestrator.components.kinds import FMU_KINDS
from orchestrator.scenario.config import Config, ConfigError

if TYPE_CHECKING:
    from orchestrator.execution.run import RunResult
    from orchestrator.observers.foxglove_view import FoxgloveView

RUN_ENGINES = ("native", "python")  # --engine; --monolithic picks the third engine (run.ENGINES)


def build(
    out_dir: Annotated[Path, typer.Option("--out", help="folder for Vehicle.fmu, VirtualTarget.fmu, Link.fmu and LiveVehicle.fmu")] = Path("build/fmus"),
    force: Annotated[bool, typer.Option(help="rebuild even if up to date")] = False,
    all_platforms: Annotated[bool, typer.Option("--all-platforms", help="native FMUs with binaries for x86_64 and aarch64 Linux, x86_64 Windows, x86_64 and aarch64 macOS, cross-compiled with Zig (pip install 'platoon-cosim[release]')")] = False,
) -> None:
    """Build the Vehicle, VirtualTarget, Link and LiveVehicle FMUs, and the native Vehicle, VirtualTarget and Link into OUT/native (FMI 2.0) and OUT/fmi3 (FMI 3.0) (only when their sources changed)."""
    from fmus.builders import ALL_FMUS, PYTHONFMU

    try:
        built_fmus = PYTHONFMU.build(out_dir, force=force, names=ALL_FMUS)
    except OSError as error:  # a full disk, a read-only folder ...: the FMUs already in place are untouched
        where = f" {error.filename}" if error.filename else ""
        fail(2, f"build --out {out_dir}: cannot write the FMUs{where}: {error.strerror or error}")
    for built in built_fmus:
        state = "built" if built.rebuilt else "up to date"
        out.print(f"{built.path}  {built.guid}  ({state})", soft_wrap=True)
    _build_native(out_dir, force, all_platforms)


def _build_native(out_dir: Path, force: bool, all_platforms: bool = False) -> None:
    """The native twins into OUT/native (FMI 2.0) and OUT/fmi3 (FMI 3.0), both by fmus/builders/native.py,
    with this machine's binary or every platform's; no compiler is one line, not a failure."""
    from fmus.builders import FMU_NAMES, LINK_FMU, BuildError, NativeBuilder, NoCompiler

    names = FMU_NAMES + (LINK_FMU,)
    try:
        built_fmus = NativeBuilder(2, all_platforms).build(out_dir / "native", force=force, names=names)
        built_fmus += NativeBuilder(3, all_platforms).build(out_dir / "fmi3", force=force, names=names)
    except NoCompiler as error:
        err.print(f"note: {error}", soft_wrap=True)
        return
    except BuildError as error:
        fail(2, f"build: {error}")
    except OSError as error:
        where = f" {error.filename}" if error.filename else ""
        fail(2, f"build --out {out_dir}: cannot write the native FMUs{where}: {error.strerror or error}")
    for built in built_fmus:
        state = "built" if built.rebuilt else "up to date"
        out.print(f"{built.path}  {built.guid}  ({state}, native{' FMI 3.0' if built.path.parent.name == 'fmi3' else ''})", soft_wrap=True)


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
    from orchestrator.observers.progress import progress
    from orchestrator.execution.run import run_scenario
    from orchestrator.scenario.scenario import step_count

    steps = step_count(config.simulation.stop_time, config.simulation.step)
    with progress(steps, "simulating", err, quiet) as tick:  # a bar on a terminal, plain lines in a pipe or a log
        return run_scenario(config, text, trace, engine=engine, tick=tick, trace_writer=trace_writer, summarize=not quiet,
                            live_view=live_view)


def run(
    config: Annotated[Path, typer.Argument(help="scenario TOML file, e.g. configs/paper/platoon.toml")],
    trace: Annotated[Optional[Path], typer.Option("--out", help="trace file (default runs/<name>-<time>.mcap)")] = None,
    overrides: Annotated[list[str], typer.Option("--set", metavar=SET_METAVAR, help="override a key, e.g. --set platoon.law=regular")] = [],
    monolithic: Annotated[bool, typer.Option("--monolithic", help="integrate the whole platoon as one system (reference)")] = False,
    compare: Annotated[bool, typer.Option("--compare-monolithic", help="also run the monolithic reference and print the largest deviations")] = False,
    quiet: Annotated[bool, typer.Option("--quiet", "-q", help="no progress bar and no table")] = False,
    trace_every: Annotated[Optional[int], typer.Option("--trace-every", min=1, help="record every K-th communication point (overrides simulation.trace_every)")] = None,
    engine_name: Annotated[Optional[str], typer.Option("--engine", metavar=choices_metavar(RUN_ENGINES), help="native (compiled stepping core; default when built) or python (FMPy); same results")] = None,
    fmu_kind: Annotated[Optional[str], typer.Option("--fmus", metavar=choices_metavar(FMU_KINDS), help="native (C FMUs, default where a C compiler can build them) or python (pythonfmu FMUs); same results (overrides simulation.fmus)")] = None,
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
    from orchestrator.support.startup import loading_a_run, seconds_since_process_start

    entered = seconds_since_process_start()  # the interpreter and the imports so far
    if trace_every is not None:
        overrides = [*overrides, f"simulation.trace_every={trace_every}"]
    check_choice("--fmus", fmu_kind, FMU_KINDS)
    if fmu_kind is not None:
        overrides = [*overrides, f"simulation.fmus={json.dumps(fmu_kind)}"]
    parsed, text = load_config(config, overrides, allow_long)
    loaded = seconds_since_process_start()
    with loading_a_run():  # one BLAS thread, no garbage collection while the run's modules load
        from orchestrator.execution.run import default_trace_path

    imported = seconds_since_process_start()  # the engines, numpy, the trace writer
    engine = _chosen_engine(config, parsed, engine_name, monolithic, trace_writer, compare)
    view = _live_view(parsed, live, live_port, live_host, live_speed, live_wait)
    target = claim_trace(trace, overwrite, [config], lambda: default_trace_path(parsed, engine))
    trace = target.final
    reference_path = trace.with_name(trace.stem + "-monolithic.mcap")
    if compare:  # checked now, claimed when its turn comes (no empty aside file if the run fails)
        check_output(reference_path, overwrite, [config])
    result = _run_with_view(config, parsed, text, target, engine, quiet, trace_writer, view)
    _report_run(result, trace, parsed, engine, quiet)
    if verbose:
        err.print(_time_split(entered, loaded, imported, result.timings, seconds_since_process_start()), highlight=False)
    if compare:
        _compare_monolithic(config, parsed, text, result, reference_path, overwrite, quiet)


def _chosen_engine(config: Path, parsed: Config, engine_name: str | None, monolithic: bool, trace_writer: str,
                   compare: bool = False) -> str:
    """The engine `platoon run` uses, after checking the options that choose it; exit 2 naming a bad one."""
    from orchestrator.components.live import LiveRunError, check_live_options
    from orchestrator.execution.run import TRACE_WRITERS, default_engine

    if engine_name is not None and engine_name not in RUN_ENGINES:
        check_choice("--engine", engine_name, RUN_ENGINES)
    if engine_name == "native" and default_engine() != "native":
        fail(2, "--engine native: the compiled core is not built here (reinstall with a C compiler: pip install -e .)")
    if trace_writer not in TRACE_WRITERS:
        fail(2, f"--trace-writer {trace_writer!r}: expected one of {', '.join(TRACE_WRITERS)}")
    engine = "monolithic" if monolithic else (engine_name or default_engine(parsed))
    if monolithic or compare:
        from orchestrator.scenario.scenario import monolithic_refusal

        refusal = monolithic_refusal(parsed)
        if refusal is not None:
            fail(2, f"config {config}: {'--monolithic' if monolithic else '--compare-monolithic'}: {refusal}")
    try:
        check_live_options(parsed, engine, trace_writer)
    except LiveRunError as error:
        fail(2, f"config {config}: {error}")
    return engine


def _live_view(parsed: Config, live: bool, port: int, host: str, speed: float, wait: bool) -> "FoxgloveView | None":
    """The --live view, started before the trace is claimed: a port in use stops the run with nothing written."""
    if not live and (port, host, speed, wait) != (8765, "127.0.0.1", 1.0, False):
        fail(2, "--live-port, --live-host, --live-speed and --live-wait go with --live (add it to watch the run)")
    if not live:
        return None
    from orchestrator.observers.foxglove_view import FoxgloveViewError, start_foxglove_view

    try:
        return start_foxglove_view(parsed, host, port, speed, err, wait)
    except FoxgloveViewError as error:
        fail(2, str(error))
    return None  # not reached: fail exits


def _run_with_view(config: Path, parsed: Config, text: str, target, engine: str, quiet: bool, trace_writer: str,
                   view: "FoxgloveView | None") -> "RunResult":
    """The run itself (with its view, announced first and closed after); exit 2 if its FMUs cannot be had."""
    from fmus.builders import BuildError

    from orchestrator.components.kinds import FmuKindError

    if view is not None:
        from orchestrator.observers.foxglove_view import announce

        announce(view, target.final, parsed, out)
    try:
        return _execute(parsed, text, target, engine, quiet, trace_writer, view)
    except (FmuKindError, BuildError) as error:  # nothing was run, the trace path is released
        fail(2, f"config {config}: {error}")
    finally:
        if view is not None:
            view.close()
            if (lag := view.lag_note()) is not None:
                err.print(lag, highlight=False, soft_wrap=True)
    raise AssertionError("not reached: fail exits")


def _report_run(result: "RunResult", trace: Path, parsed: Config, engine: str, quiet: bool) -> None:
    """The layout beside the trace, the live link table, the summary and where the trace is; a run that did
    not complete exits 1 (130/143 when stopped by a signal) naming why."""
    from orchestrator.trace.layout import write_run_layout

    written = write_run_layout(trace, parsed)  # beside the trace; a failed or stopped run says only that
    if written.warning is not None and result.status == "completed":
        err.print(written.warning, highlight=False, soft_wrap=True)
    if result.live:
        from orchestrator.cli.hil import live_table

        out.print(live_table(result.live))
    if result.status == "interrupted":
        fail(128 + (result.signal or 2), f"run {result.status}: {result.error} (trace up to that point: {result.trace})")
    if result.status != "completed":
        fail(1, f"run {result.status}: {result.error} (trace up to that point: {result.trace})")
    if not quiet:
        from orchestrator.analysis.metrics import summarize
        from orchestrator.trace import load

        # accumulated while stepping; the trace is read again only if the run's end was not the planned one
        summaries = result.summary if result.summary is not None else summarize(load(result.trace), parsed)
        out.print(summary_table(summaries, parsed, f"{parsed.name}: {parsed.platoon.law} law, {engine} engine, {result.fmus} FMUs, {parsed.simulation.stop_time:g} s"))
    out.print(f"trace: {result.trace}  ({result.steps} steps in {result.wall_time:.2f} s)", highlight=False, soft_wrap=True)
    if written.path is not None:
        out.print(f"layout: {written.path}  (open both in Foxglove: docs/foxglove.md)", highlight=False, soft_wrap=True)  # one line in a log


def _compare_monolithic(config: Path, parsed: Config, text: str, result: "RunResult", reference_path: Path,
                        overwrite: bool, quiet: bool) -> None:
    """--compare-monolithic: run the reference and print the largest deviations from it."""
    from orchestrator.analysis.compare import deviations
    from orchestrator.trace import load

    reference = _execute(parsed, text, claim_trace(reference_path, overwrite, [config], None), "monolithic", quiet)
    if reference.status != "completed":
        fail(1, f"monolithic reference {reference.status}: {reference.error}")
    worst = deviations(load(result.trace), load(reference.trace))
    out.print(
        f"largest deviation from the monolithic run ({reference.trace}): "
        f"position {worst.position:.3e} m ({worst.position_where}), gap {worst.gap:.3e} m, speed {worst.speed:.3e} m/s"
    )


def analyze(
    config: Annotated[Path, typer.Argument(help="scenario TOML file")],
    overrides: Annotated[list[str], typer.Option("--set", metavar=SET_METAVAR, help="override a key, as for platoon run")] = [],
    string_stability: Annotated[bool, typer.Option(help="also run the scenario and report peak-error ratios")] = True,
    allow_long: AllowLong = False,
) -> None:
    """Linearize about the circular equilibrium; eigenvalues next to the paper's eq. 9; string stability."""
    from orchestrator.analysis.error_gains import string_stability_report
    from orchestrator.analysis.linear import eigen_report
    from orchestrator.analysis.string_stability import chain_report
    from orchestrator.scenario.limits import check_analyze_size, check_run_size

    parsed, text = load_config(config, overrides)
    if not allow_long:
        try:
            check_analyze_size(parsed)
            if string_stability and parsed.disturbance:  # only then is the scenario run (twice)
                check_run_size(parsed)
        except ConfigError as error:
            fail(2, f"config {config}: {error}")
    paper = all(parsed.speed_law_of(i) == "paper" for i in range(1, parsed.platoon.count + 1))
    if paper and parsed.path.kind == "circle":
        out.print(eigen_report(parsed), highlight=False, soft_wrap=True)
    elif parsed.platoon.count < 2:
        fail(2, f"config {config}: path.kind = 'line': the analysis linearizes about the circular equilibrium; use a circle")
    else:  # the linearization about the circle is the paper's law's; the speed chain below is every law's, on any path
        why = "path.kind = 'line' (it linearizes about the circle)" if paper else (
            f"platoon.speed_law = {parsed.platoon.speed_law!r} (it knows only the paper's law)")
        out.print(f"eigenvalues: not for {why}; the speed chain:", highlight=False, soft_wrap=True)
    if parsed.platoon.count > 1:
        out.print(chain_report(parsed), highlight=False, soft_wrap=True)
    if string_stability:
        from orchestrator.observers.progress import progress

        shown = lambda label, total: progress(total, label, err)  # noqa: E731  (the runs: bar or plain lines)
        out.print(string_stability_report(parsed, text, shown), highlight=False, soft_wrap=True)

