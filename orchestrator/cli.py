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
from pathlib import Path
from typing import Annotated, Optional

import typer
from rich.console import Console
from rich.markup import escape
from rich.progress import BarColumn, Progress, TextColumn, TimeElapsedColumn, TimeRemainingColumn
from rich.table import Table

from .bench import ENGINES as BENCH_ENGINES
from .config import Config, ConfigError, parse_config, read_config_text

app = typer.Typer(
    add_completion=False,
    no_args_is_help=True,
    help="Platoon co-simulation: trajectory-shaping guidance FMUs, config-driven runs, MCAP traces.",
)
# No rich markup in what we print: names, paths and config text are the user's ("[[disturbance]]",
# "runs/[a]/x.mcap") and must appear as written. The one styled line (_fail) asks for markup itself.
out = Console(markup=False)
err = Console(stderr=True, markup=False)
AllowLong = Annotated[bool, typer.Option("--allow-long", help="run even above the size limits (docs/config.md: more than "
                                         "1e6 steps, 1000 substeps per step or 1e8 FMU-substeps)")]


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
    return parsed, text


@app.command()
def build(
    out_dir: Annotated[Path, typer.Option("--out", help="folder for Vehicle.fmu and VirtualTarget.fmu")] = Path("build/fmus"),
    force: Annotated[bool, typer.Option(help="rebuild even if up to date")] = False,
) -> None:
    """Build the Vehicle and VirtualTarget FMUs (only when their sources changed)."""
    from fmus.build import build_fmus

    for built in build_fmus(out_dir, force=force):
        state = "built" if built.rebuilt else "up to date"
        out.print(f"{built.path}  {built.guid}  ({state})")


def _progress_runner(steps: int, quiet: bool):
    if quiet or not sys.stderr.isatty() and not sys.stdout.isatty():
        return None, None
    progress = Progress(
        TextColumn("[bold]{task.description}"),
        BarColumn(),
        TextColumn("{task.percentage:>5.1f}%"),
        TimeElapsedColumn(),
        TimeRemainingColumn(),
        console=err,
        transient=True,
    )
    return progress, progress.add_task("simulating", total=steps)


def _summary_table(summaries, config: Config, title: str) -> Table:
    table = Table(title=title, title_justify="left")
    # units on a second header line: the table fits 80 columns (they used to vanish as rich markup)
    for column in ("vehicle", "path offset\n[m]", "gap - d*\n[m]", "speed - V_c\n[m/s]", "max |path error|\n[m]"):
        table.add_column(column, justify="right" if column != "vehicle" else "left")
    for s in summaries:
        table.add_row(
            s.name, f"{s.path_offset:+.3e}", f"{s.gap - config.platoon.d_star:+.3e}",
            f"{s.speed - config.platoon.speed:+.3e}", f"{s.path_error_max:.3e}",
        )
    return table


def _execute(config: Config, text: str, trace: Path, engine: str, quiet: bool, trace_writer: str = "auto"):
    from .run import run_scenario
    from .scenario import step_count

    steps = step_count(config.simulation.stop_time, config.simulation.step)
    progress, task = _progress_runner(steps, quiet)
    tick = None
    if progress is not None:
        every = max(1, steps // 200)

        def update(k: int) -> None:
            if k % every == 0 or k == steps:
                progress.update(task, completed=k)

        tick = update
        progress.start()
    try:
        return run_scenario(config, text, trace, engine=engine, tick=tick, trace_writer=trace_writer)
    finally:
        if progress is not None:
            progress.stop()


def _check_writable(trace: Path) -> None:
    """Fail before any work when the trace cannot be created (missing permission, a file as folder ...)."""
    try:
        trace.parent.mkdir(parents=True, exist_ok=True)
        with open(trace, "ab"):
            pass
    except OSError as error:
        _fail(2, f"--out {trace}: cannot write the trace there: {error.strerror or error}")


@app.command()
def run(
    config: Annotated[Path, typer.Argument(help="scenario TOML file, e.g. configs/paper/platoon.toml")],
    trace: Annotated[Optional[Path], typer.Option("--out", help="trace file (default runs/<name>-<time>.mcap)")] = None,
    overrides: Annotated[list[str], typer.Option("--set", help="override a key, e.g. --set platoon.law=regular")] = [],
    monolithic: Annotated[bool, typer.Option("--monolithic", help="integrate the whole platoon as one system (reference)")] = False,
    compare: Annotated[bool, typer.Option("--compare-monolithic", help="also run the monolithic reference and print the largest deviations")] = False,
    quiet: Annotated[bool, typer.Option("--quiet", "-q", help="no progress bar and no table")] = False,
    trace_every: Annotated[Optional[int], typer.Option("--trace-every", min=1, help="record every K-th communication point (overrides simulation.trace_every)")] = None,
    engine_name: Annotated[Optional[str], typer.Option("--engine", help="native (compiled stepping core; default when built) or python (FMPy); same results")] = None,
    trace_writer: Annotated[str, typer.Option("--trace-writer", help="where the trace is encoded: process (a second process), inline, or auto (a second process for long runs on a multi-core machine); same file")] = "auto",
    allow_long: AllowLong = False,
) -> None:
    """Run a scenario: wire the FMUs as the paper's Fig. 2, step them, write an MCAP trace."""
    from .metrics import summarize
    from .run import default_trace_path
    from .trace import load

    if trace_every is not None:
        overrides = [*overrides, f"simulation.trace_every={trace_every}"]
    parsed, text = _load(config, overrides, allow_long)
    from .run import default_engine

    if engine_name not in (None, "native", "python"):
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
    trace = trace or default_trace_path(parsed, engine)
    _check_writable(trace)
    result = _execute(parsed, text, trace, engine, quiet, trace_writer)
    if result.live:
        from .hil_cli import live_table

        out.print(live_table(result.live))
    if result.status == "interrupted":
        _fail(128 + (result.signal or 2), f"run {result.status}: {result.error} (trace up to that point: {result.trace})")
    if result.status != "completed":
        _fail(1, f"run {result.status}: {result.error} (trace up to that point: {result.trace})")
    if not quiet:
        summaries = summarize(load(result.trace), parsed)
        out.print(_summary_table(summaries, parsed, f"{parsed.name}: {parsed.platoon.law} law, {engine}, last 10 % of {parsed.simulation.stop_time:g} s"))
    out.print(f"trace: {result.trace}  ({result.steps} steps in {result.wall_time:.2f} s)")
    if compare:
        from .compare import deviations

        reference_path = trace.with_name(trace.stem + "-monolithic.mcap")
        reference = _execute(parsed, text, reference_path, "monolithic", quiet)
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
    from .config import config_from_mapping
    from .metrics import report_json, summarize

    loaded = _load_trace(trace)
    if loaded.config is None:
        _fail(2, f"trace {trace}: has no platoon.config metadata (not written by platoon run?)")
    config = config_from_mapping(loaded.config)
    summaries = summarize(loaded, config)
    if as_json:
        out.print_json(json.dumps(report_json(summaries)))
    else:
        out.print(_summary_table(summaries, config, f"{trace.name}: {config.platoon.law} law ({loaded.run.get('status', '?')})"))
    if plots is not None:
        from .plots import write_plots

        for path in write_plots(loaded, config, plots):
            (err if as_json else out).print(f"wrote {path}")


def _load_trace(trace: Path):
    from .trace import load

    if not trace.is_file():
        _fail(2, f"trace {trace}: no such file")
    try:
        return load(trace)
    except Exception as error:  # any reader failure means the file is not a usable trace
        _fail(2, f"trace {trace}: not a readable MCAP trace ({error})")


@app.command()
def export(
    trace: Annotated[Path, typer.Argument(help="trace written by `platoon run`")],
    csv_dir: Annotated[Path, typer.Option("--csv", help="folder for one CSV per component (header: t, then the outputs)")],
) -> None:
    """Export a trace: one CSV per component (t, then its outputs) and errors.csv (path, gap, speed errors)."""
    from .trace import export_csv

    loaded = _load_trace(trace)
    for path in export_csv(loaded, csv_dir):
        out.print(f"wrote {path}", highlight=False, soft_wrap=True)


trace_app = typer.Typer(no_args_is_help=True, help="Work on trace files.")
app.add_typer(trace_app, name="trace")


@trace_app.command("recover")
def trace_recover(
    broken: Annotated[Path, typer.Argument(help="an unfinished trace (the run was killed)")],
    fixed: Annotated[Optional[Path], typer.Option("--out", help="recovered trace (default BROKEN-recovered.mcap)")] = None,
) -> None:
    """Rewrite the complete chunks of an unfinished trace into a valid one (losing at most the last chunk)."""
    from .trace import TraceError, recover

    if not broken.is_file():
        _fail(2, f"trace {broken}: no such file")
    fixed = fixed or broken.with_name(broken.stem + "-recovered.mcap")
    if fixed.resolve() == broken.resolve():
        _fail(2, f"--out {fixed}: must differ from the trace being recovered")
    try:
        result = recover(broken, fixed)
    except TraceError as error:
        _fail(2, str(error))
    if result.steps == 0:
        _fail(1, f"trace {broken}: no complete communication point to recover ({result.chunks} complete chunks); wrote {fixed} with its metadata only")
    span = f"t = 0 .. {result.last_time:.6g} s" if result.last_time is not None else "no time"
    state = "a complete file" if result.finished else f"{result.chunks} complete chunks"
    out.print(f"recovered {result.steps} communication points ({span}, {result.messages} messages) from {state}: {fixed}",
              highlight=False, soft_wrap=True)


@app.command()
def analyze(
    config: Annotated[Path, typer.Argument(help="scenario TOML file")],
    overrides: Annotated[list[str], typer.Option("--set", help="override a key")] = [],
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
        out.print(string_stability_report(parsed, text), highlight=False, soft_wrap=True)


bench_app = typer.Typer(no_args_is_help=True, help="Benchmarks of issue 10 (JSON under runs/bench/; not pass/fail tests).")
app.add_typer(bench_app, name="bench")

ROUNDS_HELP = "interleaved repetitions (each variant once per round, order rotated); medians over rounds"
OutDir = Annotated[Path, typer.Option("--out-dir", help="folder for the JSON results")]
Quiet = Annotated[bool, typer.Option("--quiet", "-q", help="no progress, only the tables and the result file")]
Engines = Annotated[str, typer.Option(help=f"comma-separated, of: {', '.join(BENCH_ENGINES)}")]
Counts = Annotated[str, typer.Option("--n", help="comma-separated vehicle counts")]
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


def _per_fmu_step(suite_name: str, engines: str, n: str, steps: int, rounds: int, out_dir: Path, quiet: bool) -> None:
    """The two suites of FMU-step costs (``steps``, ``coupling``): same options, same checks."""
    from importlib import import_module

    suite = import_module(f".bench.{suite_name}", __package__)
    chosen, counts = _csv("--engines", engines, BENCH_ENGINES), _counts(n)
    _bench(suite_name, lambda progress: suite.run(chosen, counts, steps, rounds, progress=progress), suite.markdown,
           out_dir, quiet)


@bench_app.command("steps")
def bench_steps(engines: Engines = "native,python,fmpy-bare,libcosim,libcosim-0threads,slaves",
                n: Counts = "4,16,64,256", steps: Steps = 1000, rounds: Rounds = 5,
                out_dir: OutDir = Path("runs/bench"), quiet: Quiet = False) -> None:
    """Microseconds per FMU-step of our engines, the bare FMPy loop, libcosim and the floor, by N."""
    _per_fmu_step("steps", engines, n, steps, rounds, out_dir, quiet)


@bench_app.command("coupling")
def bench_coupling(engines: Engines = "native,slaves", n: Counts = "4,16,64", steps: Steps = 1000, rounds: Rounds = 5,
                   out_dir: OutDir = Path("runs/bench"), quiet: Quiet = False) -> None:
    """Cost per FMU-step with coupling "hold" against "extrapolate" (same rounds, same engines)."""
    _per_fmu_step("coupling", engines, n, steps, rounds, out_dir, quiet)


@bench_app.command("scenarios")
def bench_scenarios(
    configs: Annotated[list[Path], typer.Option("--config", help="scenario TOML (repeatable; default configs/paper/*.toml)")] = [],
    engines: Annotated[str, typer.Option(help="comma-separated: native, python")] = "native,python",
    variants: Annotated[str, typer.Option(help="comma-separated: cli-traced (platoon run --out X -q), traced, untraced")] = "cli-traced,traced,untraced",
    rounds: Rounds = 3,
    overrides: Annotated[list[str], typer.Option("--set", help="override a key in every scenario")] = [],
    out_dir: OutDir = Path("runs/bench"),
    quiet: Quiet = False,
) -> None:
    """Whole-run wall times of the paper's scenarios, start-up included, traced and untraced."""
    from .bench import scenarios as suite

    chosen = _csv("--engines", engines, suite.ENGINES)
    kinds = _csv("--variants", variants, suite.VARIANTS)
    _bench("scenarios", lambda progress: suite.run(configs or None, chosen, kinds, rounds, overrides, progress=progress),
           suite.markdown, out_dir, quiet)


@bench_app.command("instances")
def bench_instances(
    engines: Annotated[str, typer.Option(help="comma-separated: native, fmpy")] = "native,fmpy",
    n: Counts = "4,16,64,256",
    wirings: Annotated[str, typer.Option(help="comma-separated: instances (unconnected), platoon (wired, settle sweeps)")] = "instances,platoon",
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
    engines: Annotated[str, typer.Option(help="comma-separated: native, python, fmpy-bare")] = "native",
    fmu_steps: Annotated[int, typer.Option(min=1, help="FMU-steps per measurement (steps = this / (N + 1))")] = 2500,
    ll: Annotated[str, typer.Option("--ll", help="comma-separated last-level caches to simulate: l2 (this machine's "
                                               "512 KiB L2), detected (valgrind's choice, the L3)")] = "l2",
    cores: Annotated[list[str], typer.Option("--core", help=f"{CORE_BUILD_HELP}; repeatable (native engine; default: the installed core)")] = [],
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
