"""What `platoon run` does once its options are parsed: load the config, choose the engine, claim the
trace, run (with its progress, live view and optional monolithic comparison), report.

Neither typer nor rich is imported here: the same ``run_command`` serves the typer command
(orchestrator/cli/run.py) and the fast start (orchestrator/cli/launch.py), which parses a plain
`platoon run` command line itself. rich is loaded only for what needs it: a progress bar, the summary
table, an error line, a line rich would print differently (orchestrator/cli/plain.py).
"""

from __future__ import annotations

import json
import time as clock
from pathlib import Path
from typing import TYPE_CHECKING

from orchestrator.cli.options import RunOptions
from orchestrator.cli.plain import (check_choice, check_output, claim_trace, console, fail, load_config, run_inputs,
                                    say)
from orchestrator.components.kinds import FMU_KINDS
from orchestrator.scenario.config_text import header_text

if TYPE_CHECKING:
    from orchestrator.scenario.config import Config
    from orchestrator.execution.run import RunResult
    from orchestrator.observers.foxglove_view import FoxgloveView

RUN_ENGINES = ("native", "python")  # --engine; --monolithic picks the third engine (run.ENGINES)
TRACE_WRITER_CHOICES = ("auto", "inline", "process")  # --trace-writer (checked against run.TRACE_WRITERS)


def run_command(options: RunOptions) -> None:
    """Run a scenario: wire the FMUs as the paper's Fig. 2, step them, write an MCAP trace."""
    from orchestrator.support.startup import loading_a_run, seconds_since_process_start

    entered, entered_at = seconds_since_process_start(), clock.perf_counter()  # the interpreter and the imports so far
    config, overrides = options.config, list(options.overrides)
    if options.trace_every is not None:
        overrides = [*overrides, f"simulation.trace_every={options.trace_every}"]
    check_choice("--fmus", options.fmu_kind, FMU_KINDS)
    if options.fmu_kind is not None:
        overrides = [*overrides, f"simulation.fmus={json.dumps(options.fmu_kind)}"]
    # a config validated before comes back without pydantic, except for the paths not written for it
    cached = not (options.live or options.monolithic or options.compare)
    parsed, text = load_config(config, overrides, options.allow_long, cached)
    loaded = seconds_since_process_start()
    with loading_a_run():  # one BLAS thread, no garbage collection while the run's modules load
        from orchestrator.execution.run import default_trace_path

    imported = seconds_since_process_start()  # the engines, numpy, the trace writer
    engine = _chosen_engine(config, parsed, options.engine_name, options.monolithic, options.trace_writer,
                            options.compare, tuple(o.split("=", 1)[0].strip() for o in overrides if o.startswith("links")))
    view = _live_view(parsed, options)
    inputs = run_inputs(config, parsed)
    target = claim_trace(options.trace, options.overwrite, inputs, lambda: default_trace_path(parsed, engine))
    trace = target.final
    reference_path = trace.with_name(trace.stem + "-monolithic.mcap")
    if options.compare:  # checked now, claimed when its turn comes (no empty aside file if the run fails)
        check_output(reference_path, options.overwrite, inputs)
    if parsed.live_vehicles():  # where to put each robot, before the run waits for it
        from orchestrator.components.live import start_pose_lines

        for line in start_pose_lines(parsed):
            say(line, stderr=True)
    result = _run_with_view(config, parsed, text, target, engine, options.quiet, options.trace_writer, view)
    first_step = _first_step(entered, entered_at, result, clock.perf_counter())
    pace = 1.0 if result.live else (options.live_speed if options.live and options.live_speed > 0 else None)
    _report_run(result, trace, parsed, engine, options.quiet, pace)
    if options.verbose:
        split = _time_split(entered, loaded, imported, result.timings, seconds_since_process_start(), first_step)
        console(stderr=True).print(split, highlight=False)
    if options.compare:
        _compare_monolithic(config, parsed, text, result, reference_path, options.overwrite, options.quiet)


def _first_step(entered: float | None, entered_at: float, result: "RunResult", returned_at: float) -> float | None:
    """Seconds from the process's start to the first step: the run's start (its return less its wall time)
    plus its setup and initialization, on the clock read when the run command was entered."""
    if entered is None or "setup" not in result.timings or "initialize" not in result.timings:
        return None
    stepping_at = returned_at - result.wall_time + result.timings["setup"] + result.timings["initialize"]
    return entered + (stepping_at - entered_at)


def _time_split(entered: float | None, loaded: float | None, imported: float | None, timings: dict[str, float],
                now: float | None, first_step: float | None = None) -> str:
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
        f"  the first step began {seconds(first_step)} after the process started",
        f"  after the run (summary, output): {seconds(rest)}",
    ])


def _execute(config: Config, text: str, trace, engine: str, quiet: bool, trace_writer: str = "auto", live_view=None):
    from orchestrator.observers.progress import progress
    from orchestrator.execution.run import run_scenario
    from orchestrator.scenario.scenario import step_count

    steps = step_count(config.simulation.stop_time, config.simulation.step)
    shown_on = None if quiet else console(stderr=True)  # a bar on a terminal, plain lines in a pipe or a log
    with progress(steps, "simulating", shown_on, quiet) as tick:
        return run_scenario(config, text, trace, engine=engine, tick=tick, trace_writer=trace_writer, summarize=not quiet,
                            live_view=live_view)


def _chosen_engine(config: Path, parsed: Config, engine_name: str | None, monolithic: bool, trace_writer: str,
                   compare: bool = False, set_links: tuple[str, ...] = ()) -> str:
    """The engine `platoon run` uses, after checking the options that choose it; exit 2 naming a bad one
    (``set_links``: the --set keys under links, which a refused monolithic run names)."""
    from orchestrator.components.live import LiveRunError, check_live_options
    from orchestrator.components.remote import RemoteRunError, check_remote_options
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

        refusal = monolithic_refusal(parsed, set_links)
        if refusal is not None:
            fail(2, f"config {config}: {'--monolithic' if monolithic else '--compare-monolithic'}: {refusal}")
    try:
        check_live_options(parsed, engine, trace_writer)
        check_remote_options(parsed, engine)
    except (LiveRunError, RemoteRunError) as error:
        fail(2, f"config {config}: {error}")
    return engine


def _live_view(parsed: Config, options: RunOptions) -> "FoxgloveView | None":
    """The --live view, started before the trace is claimed: a port in use stops the run with nothing written."""
    live, port, host, speed, wait = (options.live, options.live_port, options.live_host, options.live_speed,
                                     options.live_wait)
    if not live and (port, host, speed, wait) != (8765, "127.0.0.1", 1.0, False):
        fail(2, "--live-port, --live-host, --live-speed and --live-wait go with --live (add it to watch the run)")
    if not live:
        return None
    from orchestrator.observers.foxglove_view import FoxgloveViewError, start_foxglove_view

    try:
        return start_foxglove_view(parsed, host, port, speed, console(stderr=True), wait)
    except FoxgloveViewError as error:
        fail(2, str(error))
    return None  # not reached: fail exits


def _run_with_view(config: Path, parsed: Config, text: str, target, engine: str, quiet: bool, trace_writer: str,
                   view: "FoxgloveView | None") -> "RunResult":
    """The run itself (with its view, announced first and closed after); exit 2 if its FMUs cannot be had."""
    from fmus.builders import BuildError

    from orchestrator.components.kinds import FmuKindError
    from orchestrator.support.output import OutputError

    if view is not None:
        from orchestrator.observers.foxglove_view import announce

        announce(view, target.final, parsed, console())
    try:
        return _execute(parsed, text, target, engine, quiet, trace_writer, view)
    except (FmuKindError, BuildError) as error:  # nothing was run, the trace path is released
        fail(2, f"config {config}: {error}")
    except OutputError as error:  # a FIFO, device or folder where an FMU is built: one line naming it
        fail(2, str(error))
    finally:
        if view is not None:
            view.close()
            if (lag := view.lag_note()) is not None:
                say(lag, stderr=True)
    raise AssertionError("not reached: fail exits")


def _report_run(result: "RunResult", trace: Path, parsed: Config, engine: str, quiet: bool,
                pace: float | None = None) -> None:
    """The layout beside the trace, the live link table, the summary and where the trace is (with ``pace``, the
    speed a run was paced to the wall clock at, where its time went); a run that did not complete exits 1
    (130/143 when stopped by a signal) naming why."""
    from orchestrator.trace.layout import write_run_layout

    written = write_run_layout(trace, parsed)  # beside the trace; a failed or stopped run says only that
    if written.warning is not None and result.status == "completed":
        say(written.warning, stderr=True)
    if result.live:
        from orchestrator.cli.hil import live_table

        console().print(live_table(result.live))
    if result.status == "interrupted":
        fail(128 + (result.signal or 2), f"run {result.status}: {result.error} (trace up to that point: {result.trace})")
    if result.status != "completed":
        fail(1, f"run {result.status}: {result.error} (trace up to that point: {result.trace})")
    if not quiet:
        from orchestrator.analysis.metrics import summarize
        from orchestrator.cli.tables import summary_table
        from orchestrator.trace import load

        # accumulated while stepping; the trace is read again only if the run's end was not the planned one
        summaries = result.summary if result.summary is not None else summarize(load(result.trace), parsed)
        console().print(summary_table(summaries, parsed, f"{parsed.name}: {header_text(parsed)}, {engine} engine, {result.fmus} FMUs, {parsed.simulation.stop_time:g} s"))
        if result.links:
            from orchestrator.cli.tables import link_table

            console().print(link_table(result.links))
    if result.departures:  # said even with --quiet: the run completed, but not as the model
        from orchestrator.analysis.validity import departures_lines

        for line in departures_lines(result.departures):
            say(line, stderr=True)
    say(f"trace: {result.trace}  ({result.steps} steps in {result.working_time:.2f} s)")  # waits for a viewer or robot left out
    if pace is not None and "steps" in result.timings:
        say(paced_time_text(result, parsed.simulation.stop_time / pace))
    if written.path is not None:
        say(f"layout: {written.path}  (open both in Foxglove: docs/foxglove.md)")  # one line in a log


def paced_time_text(result: "RunResult", paced: float) -> str:
    """Where a paced run's "N steps in X s" went: ``paced`` s of wall clock the stepping was held to, how far
    behind it the last step ended (a run that fell behind says so), and the start and finish around it."""
    stepping = result.timings["steps"]
    late = stepping - paced
    behind = (f", so the run ended {late:.2f} s behind the pace: it fell behind (a loaded machine)" if late >= 0.1
              else "")
    return (f"paced: {paced:g} s of simulated time on the wall clock; stepping took {stepping:.2f} s{behind}; "
            f"starting and finishing {result.working_time - stepping:.2f} s")


def _compare_monolithic(config: Path, parsed: Config, text: str, result: "RunResult", reference_path: Path,
                        overwrite: bool, quiet: bool) -> None:
    """--compare-monolithic: run the reference and print the largest deviations from it."""
    from orchestrator.analysis.compare import deviations
    from orchestrator.trace import load

    reference = _execute(parsed, text, claim_trace(reference_path, overwrite, run_inputs(config, parsed), None), "monolithic", quiet)
    if reference.status != "completed":
        fail(1, f"monolithic reference {reference.status}: {reference.error}")
    worst = deviations(load(result.trace), load(reference.trace))
    console().print(
        f"largest deviation from the monolithic run ({reference.trace}): "
        f"position {worst.position:.3e} m ({worst.position_where}), gap {worst.gap:.3e} m, speed {worst.speed:.3e} m/s"
    )


