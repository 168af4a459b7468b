"""`platoon build`, `platoon run` and `platoon analyze`: build the FMUs, run a scenario (with its progress,
summary, layout and optional monolithic comparison), linearize a config."""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING, Annotated, Optional

import typer

from orchestrator.cli.common import AllowLong, OVERWRITE_HELP, SET_METAVAR, choices_metavar, err, fail, load_config, out
from orchestrator.cli.options import RunOptions
from orchestrator.cli.running import RUN_ENGINES, TRACE_WRITER_CHOICES, run_command
from orchestrator.components.kinds import FMU_KINDS
from orchestrator.scenario.raw_config import ConfigError

if TYPE_CHECKING:
    from orchestrator.support.output import OwnFiles


def build(
    out_dir: Annotated[Path, typer.Option("--out", help="folder for Vehicle.fmu, VirtualTarget.fmu, Link.fmu, LiveVehicle.fmu and RemoteVehicle.fmu")] = Path("build/fmus"),
    force: Annotated[bool, typer.Option(help="rebuild even if up to date")] = False,
    all_platforms: Annotated[bool, typer.Option("--all-platforms", help="native FMUs with binaries for x86_64 and aarch64 Linux, x86_64 Windows, x86_64 and aarch64 macOS, cross-compiled with Zig (pip install 'platoon-cosim[release]')")] = False,
) -> None:
    """Build the Vehicle, VirtualTarget, Link, LiveVehicle and RemoteVehicle FMUs, and the native Vehicle, VirtualTarget and Link into OUT/native (FMI 2.0) and OUT/fmi3 (FMI 3.0) (only when their sources changed)."""
    from fmus.builders import ALL_FMUS, PYTHONFMU
    from fmus.builders.base import source_files

    from orchestrator.cli.common import output_rule
    from orchestrator.support.output import OwnFiles

    rule = OwnFiles(source_files(), "build --out")  # never a source, a FIFO or a device; aside, synced, renamed
    try:
        with output_rule():
            built_fmus = PYTHONFMU.build(out_dir, force=force, names=ALL_FMUS, output=rule)
    except OSError as error:  # a full disk, a read-only folder ...: the FMUs already in place are untouched
        where = f" {error.filename}" if error.filename else ""
        fail(2, f"build --out {out_dir}: cannot write the FMUs{where}: {error.strerror or error}")
    for built in built_fmus:
        state = "built" if built.rebuilt else "up to date"
        out.print(f"{built.path}  {built.guid}  ({state})", soft_wrap=True)
    _build_native(out_dir, force, all_platforms, rule)


def _build_native(out_dir: Path, force: bool, all_platforms: bool = False, rule: OwnFiles | None = None) -> None:
    """The native twins into OUT/native (FMI 2.0) and OUT/fmi3 (FMI 3.0), both by fmus/builders/native.py,
    with this machine's binary or every platform's; no compiler is one line, not a failure. With every
    platform's, Zig's cache is warmed first and each target said as it finishes (a cold cache: minutes);
    a compiler that runs past its time is one line naming the target and what to do, exit 1, and no FMU it
    was building is written."""
    from fmus.builders import FMU_NAMES, LINK_FMU, BuildError, NativeBuilder, NoCompiler
    from fmus.builders.toolchain import CompileTimeout

    from orchestrator.cli.common import output_rule

    names = FMU_NAMES + (LINK_FMU,)
    if all_platforms:  # said before it starts: a cold Zig cache makes the first such build take minutes
        err.print("note: --all-platforms cross-compiles with Zig for 5 platforms; on a machine whose Zig cache is cold "
                  "Zig first compiles its C runtimes for each target (several minutes on 2 cores, docs/fmus.md), "
                  "each target said as it finishes; later builds reuse its cache", highlight=False, soft_wrap=True)
    compiled = _say_compiled if all_platforms else None
    try:
        with output_rule():
            if all_platforms:
                _warm_zig()
            built_fmus = NativeBuilder(2, all_platforms, compiled).build(out_dir / "native", force=force, names=names,
                                                                         output=rule)
            built_fmus += NativeBuilder(3, all_platforms, compiled).build(out_dir / "fmi3", force=force, names=names,
                                                                          output=rule)
    except NoCompiler as error:
        err.print(f"note: {error}", soft_wrap=True)
        return
    except CompileTimeout as error:  # not the user's input: their machine's load, or a compiler that hangs
        fail(1, f"build{' --all-platforms' if all_platforms else ''}: {error}")
    except BuildError as error:
        fail(2, f"build: {error}")
    except OSError as error:
        where = f" {error.filename}" if error.filename else ""
        fail(2, f"build --out {out_dir}: cannot write the native FMUs{where}: {error.strerror or error}")
    for built in built_fmus:
        state = "built" if built.rebuilt else "up to date"
        out.print(f"{built.path}  {built.guid}  ({state}, native{' FMI 3.0' if built.path.parent.name == 'fmi3' else ''})", soft_wrap=True)


def _warm_zig() -> None:
    """Zig's C runtime for each release target, each said as it is ready, and while one takes long (a cold
    cache) a line after PLATOON_PROGRESS_SECONDS (at least 1 s) and each time the wait has doubled."""
    from fmus.builders.zig_cache import warm_cross_cache

    from orchestrator.observers.progress import progress_seconds

    warm_cross_cache(lambda target, seconds: err.print(f"zig: C runtime for {target} ready ({seconds:.1f} s)",
                                                       highlight=False),
                     lambda target, seconds: err.print(f"zig: building its C runtime for {target}, {seconds:.0f} s so "
                                                       "far ...", highlight=False),
                     max(1.0, progress_seconds()))


def _say_compiled(what: str, platform, seconds: float) -> None:
    err.print(f"compiled {what} for {platform.tuple} ({seconds:.1f} s)", highlight=False)


def run(
    config: Annotated[Path, typer.Argument(help="scenario TOML file, e.g. configs/paper/platoon.toml")],
    trace: Annotated[Optional[Path], typer.Option("--out", help="trace file (default: runs/ NAME-TIME.mcap, named after the config's name and the start time)")] = None,
    overrides: Annotated[list[str], typer.Option("--set", metavar=SET_METAVAR, help="override a key, e.g. --set platoon.law=regular")] = [],
    monolithic: Annotated[bool, typer.Option("--monolithic", help="integrate the whole platoon as one system (reference)")] = False,
    compare: Annotated[bool, typer.Option("--compare-monolithic", help="also run the monolithic reference and print the largest deviations")] = False,
    quiet: Annotated[bool, typer.Option("--quiet", "-q", help="no progress bar and no table")] = False,
    trace_every: Annotated[Optional[int], typer.Option("--trace-every", min=1, help="record every K-th communication point (overrides simulation.trace_every)")] = None,
    engine_name: Annotated[Optional[str], typer.Option("--engine", metavar=choices_metavar(RUN_ENGINES), help="native (compiled stepping core; default when built) or python (FMPy); same results")] = None,
    fmu_kind: Annotated[Optional[str], typer.Option("--fmus", metavar=choices_metavar(FMU_KINDS), help="native (C FMUs, default where a C compiler can build them) or python (pythonfmu FMUs); same results (overrides simulation.fmus)")] = None,
    trace_writer: Annotated[str, typer.Option("--trace-writer", metavar=choices_metavar(TRACE_WRITER_CHOICES), help="where the trace is encoded: process (a second process), inline, or auto (a second process for long runs on a multi-core machine); same file")] = "auto",
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
    run_command(RunOptions(config=config, trace=trace, overrides=overrides, monolithic=monolithic, compare=compare,
                           quiet=quiet, trace_every=trace_every, engine_name=engine_name, fmu_kind=fmu_kind,
                           trace_writer=trace_writer, overwrite=overwrite, verbose=verbose, allow_long=allow_long,
                           live=live, live_port=live_port, live_host=live_host, live_speed=live_speed,
                           live_wait=live_wait))


def analyze(
    config: Annotated[Path, typer.Argument(help="scenario TOML file")],
    overrides: Annotated[list[str], typer.Option("--set", metavar=SET_METAVAR, help="override a key, as for platoon run")] = [],
    measure: Annotated[bool, typer.Option("--measure/--no-measure", help="with a [[disturbance]]: run the scenario with and without it, report the peak deviations and the l2 and l_inf gains from vehicle to vehicle")] = True,
    old_measure: Annotated[Optional[bool], typer.Option("--string-stability/--no-string-stability", hidden=True,
                                                        help="the old name of --measure/--no-measure")] = None,
    allow_long: AllowLong = False,
) -> None:
    """Analyze a config: on a circle with the paper's law, the linearization about the circular equilibrium,
    its eigenvalues next to the paper's eq. 9; for every law, on a circle or a line, the speed chain's G(jw)
    (peak gain, the time gap and delay that keep it string stable); with a [[disturbance]], the l2 and l_inf
    gains measured from vehicle to vehicle."""
    from orchestrator.analysis.chain_model import chain_model
    from orchestrator.analysis.error_gains import string_stability_report
    from orchestrator.analysis.linear import eigen_report
    from orchestrator.analysis.sizing import check_analysis, nothing_arrives
    from orchestrator.analysis.string_stability import chain_report
    from orchestrator.scenario.limits import check_analyze_size, check_run_size

    string_stability = measure if old_measure is None else old_measure
    parsed, text = load_config(config, overrides)
    measured = string_stability and bool(parsed.disturbance)  # only then is the scenario run (twice)
    chain = chain_model(parsed)  # the chain the sizing, the cascade, the loop and the scatter below all read
    try:
        check_analysis(parsed, measured, closed_form=not allow_long, chain=chain)  # sized before any work (analysis/sizing.py)
        if not allow_long:
            check_analyze_size(parsed)
            if measured:
                check_run_size(parsed)
    except ConfigError as error:
        fail(2, f"config {config}: {error}")
    answer = nothing_arrives(parsed)
    if answer is not None:  # a platoon whose links deliver nothing: answered, not divided by
        out.print(answer, highlight=False, soft_wrap=True)
        return
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
        from orchestrator.analysis.error_gains import scatter_lines
        from orchestrator.analysis.verdict import closed_form_verdict

        out.print(chain_report(parsed, chain), highlight=False, soft_wrap=True)
        out.print(closed_form_verdict(parsed, chain=chain).line(), highlight=False, soft_wrap=True)  # as stability and the map say it
        for line in scatter_lines(parsed, chain):  # a single run's predicted scatter about that mean
            out.print(line, highlight=False, soft_wrap=True)
    if string_stability:
        from orchestrator.observers.progress import progress

        shown = lambda label, total: progress(total, label, err)  # noqa: E731  (the runs: bar or plain lines)
        out.print(string_stability_report(parsed, text, shown), highlight=False, soft_wrap=True)

