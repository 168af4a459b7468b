"""`platoon report`, `platoon export` and `platoon trace recover`: read a trace back, summarize it, turn it into
CSV, rescue what a killed run or a damaged file holds."""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING, Annotated, Optional

import typer

if TYPE_CHECKING:  # rich's table is imported where used: `platoon run -q` needs none
    pass

from orchestrator.cli.common import Overwrite, err, fail, load_trace, note_recovery, out, output_rule
from orchestrator.cli.reporting import report_command, trace_and_config
from orchestrator.support.output import check_folder

def report(
    trace: Annotated[Path, typer.Argument(help="trace written by `platoon run`")],
    as_json: Annotated[bool, typer.Option("--json", help="print the summary as JSON")] = False,
    plots: Annotated[Optional[Path], typer.Option("--plots", help="write the paper's figure panels as PNG here")] = None,
    overwrite: Overwrite = False,
) -> None:
    """Summarize a trace (path offset, gap, speed, max path error) and draw the paper's panels."""
    report_command(trace, as_json, plots, overwrite)


def export(
    trace: Annotated[Path, typer.Argument(help="trace written by `platoon run`")],
    csv_dir: Annotated[Path, typer.Option("--csv", help="folder for one CSV per component (header: t, then the outputs)")],
    overwrite: Overwrite = False,
) -> None:
    """Export a trace: one CSV per component (t, then its outputs) and errors.csv (path, gap, speed errors)."""
    from orchestrator.trace import export_csv

    with output_rule():
        check_folder(csv_dir, [trace], "--csv")
    loaded = load_trace(trace)
    note_recovery(loaded, err.print)
    with output_rule():
        written = export_csv(loaded, csv_dir, overwrite, [trace])
    for path in written:
        out.print(f"wrote {path}", highlight=False, soft_wrap=True)


trace_app = typer.Typer(no_args_is_help=True, help="Work on trace files.")


def trace_recover(
    broken: Annotated[Path, typer.Argument(help="an unfinished or damaged trace (e.g. the run was killed)")],
    fixed: Annotated[Optional[Path], typer.Option("--out", help="recovered trace (default BROKEN-recovered.mcap)")] = None,
    overwrite: Overwrite = False,
) -> None:
    """Rewrite the intact chunks of an unfinished or damaged trace into a valid one; say what was lost."""
    from orchestrator.trace import TraceError, recover
    from orchestrator.trace.output import OutputError, check_in_use, check_replaceable, claim, publish
    from orchestrator.trace.recovery import describe_lost

    if not broken.is_file():
        fail(2, f"trace {broken}: no such file")
    if fixed is None:
        name = broken.name[:-len(".partial")] if broken.name.endswith(".mcap.partial") else broken.name
        fixed = broken.with_name(Path(name).stem + "-recovered.mcap")
    try:
        check_in_use(broken)
        check_replaceable(fixed, overwrite, [broken])  # an existing trace is replaced, anything else only when told
        target = claim(fixed, overwrite=True, protect=[broken], suffix=".recovering")  # a stale .recovering: ours
    except OutputError as error:
        fail(2, str(error))
    try:
        result = recover(broken, target.aside)
        publish(target.aside, target.final)
    except (TraceError, OSError) as error:
        target.aside.unlink(missing_ok=True)  # no half-written file left behind
        target.release()
        if isinstance(error, TraceError):
            fail(2, str(error))
        fail(2, f"--out {fixed}: cannot write the recovered trace: {error.strerror or error} (nothing written)")
    target.release()
    stretches = "stretch" if result.damaged == 1 else "stretches"
    damage = f"; {result.damaged} damaged {stretches} skipped, data lost between {describe_lost(result.lost)}" if result.damaged else ""
    if result.refused_copies:
        damage += (f"; {result.refused_copies} copy of the channel list refused (it contradicts the file's own "
                   "channels: spliced from another trace, or damaged)")
    if result.steps == 0:
        fail(1, f"trace {broken}: no complete communication point to recover ({result.chunks} intact chunks{damage}); "
                 f"wrote {fixed} with its metadata only")
    span = f"t = 0 .. {result.last_time:.6g} s" if result.last_time is not None else "no time"
    state = "a complete file" if result.finished else f"{result.chunks} intact chunks"
    out.print(f"recovered {result.steps} communication points ({span}, {result.messages} messages) from {state}: {fixed}"
              f"{damage}", highlight=False, soft_wrap=True)
    from shlex import quote

    out.print(f"layout: platoon layout {quote(str(fixed))}  (a Foxglove layout fitted to the run, to open with it: "
              "docs/foxglove.md)",
              highlight=False, soft_wrap=True)



def register_group(app: typer.Typer) -> None:
    """``platoon trace ...``: the commands that work on trace files."""
    trace_app.command("recover")(trace_recover)
    app.add_typer(trace_app, name="trace")


def stability(
    trace: Annotated[Path, typer.Argument(help="trace of a disturbance run (a [[disturbance]] in its config)")],
    reference: Annotated[Optional[Path], typer.Option("--reference", help="the same run without the disturbance: "
                                                      "errors against it (default: against the steady state)")] = None,
    start: Annotated[Optional[float], typer.Option("--from", help="window start, s (default: the first disturbance)")] = None,
    end: Annotated[Optional[float], typer.Option("--to", help="window end, s (default: the trace's end)")] = None,
) -> None:
    """String stability measured: l2 and l_inf gains of the speed and gap errors from vehicle to vehicle."""
    from orchestrator.analysis.error_gains import stability_report, window_of
    from orchestrator.analysis.sizing import check_analysis, nothing_arrives
    from orchestrator.trace.format import is_link

    bodies = {"components": lambda name: not is_link(name), "errors": False}  # the gains need the bodies' motion only
    loaded, config, _ = trace_and_config(trace, **bodies)
    if not loaded.vehicles() or any(len(loaded.component(v)["t"]) < 2 for v in loaded.vehicles()):
        fail(2, f"trace {trace}: fewer than two recorded points, no gains to measure")
    try:
        check_analysis(config, measured=True)  # sized before any work (analysis/sizing.py)
    except ValueError as error:
        fail(2, f"trace {trace}: {error}")
    answer = nothing_arrives(config)
    if answer is not None:  # links that deliver nothing: no chain to measure gains along
        out.print(answer, highlight=False, soft_wrap=True)
        return
    base = load_trace(reference, **bodies) if reference is not None else None
    if base is not None and base.vehicles() != loaded.vehicles():
        fail(2, f"reference {reference}: its vehicles ({', '.join(base.vehicles())}) are not the trace's")
    note_recovery(loaded, out.print)  # a hole in the window changes the gains: said, as report says it
    if base is not None:
        note_recovery(base, lambda text, **style: out.print(f"reference {reference}: {text}", **style))
    try:
        text = stability_report(loaded, config, base, window_of(config, loaded, start, end))
    except ValueError as error:
        fail(2, f"trace {trace}: {error}")
    out.print(text, highlight=False, soft_wrap=True)
