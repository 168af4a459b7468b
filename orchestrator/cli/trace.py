"""`platoon report`, `platoon export` and `platoon trace recover`: read a trace back, summarize it, turn it into
CSV, rescue what a killed run or a damaged file holds."""

from __future__ import annotations

import json
from pathlib import Path
from typing import TYPE_CHECKING, Annotated, Optional

import typer

from orchestrator.scenario.raw_config import ConfigError

if TYPE_CHECKING:  # rich's table is imported where used: `platoon run -q` needs none
    pass

from orchestrator.cli.common import (Overwrite, err, fail, load_trace, note_recovery, out, output_rule, quiet_nan,
                                     summary_table)
from orchestrator.support.output import check_folder

def _trace_and_config(trace: Path, **selection):
    """The trace read back (``selection``: what ``load`` reads of it), its config and the keys that were
    not finite; exit 2 naming what is wrong."""
    from orchestrator.scenario.stored_config import stored_config

    loaded = load_trace(trace, **selection)
    if loaded.config is None:
        fail(2, f"trace {trace}: has no platoon.config metadata (not written by platoon run?)")
    try:
        config, non_finite = stored_config(loaded.config)
    except ConfigError as error:
        fail(2, f"trace {trace}: its stored config is not valid: {error}")
    return loaded, config, non_finite


def report(
    trace: Annotated[Path, typer.Argument(help="trace written by `platoon run`")],
    as_json: Annotated[bool, typer.Option("--json", help="print the summary as JSON")] = False,
    plots: Annotated[Optional[Path], typer.Option("--plots", help="write the paper's figure panels as PNG here")] = None,
    overwrite: Overwrite = False,
) -> None:
    """Summarize a trace (path offset, gap, speed, max path error) and draw the paper's panels."""
    from orchestrator.analysis.link_stats import link_rows, link_stats_of_trace
    from orchestrator.analysis.metrics import report_json, summarize
    from orchestrator.analysis.validity import departures_lines, departures_of_trace

    if plots is not None:  # every panel's target checked before the trace is read
        from orchestrator.analysis.plots import check_plot_targets

        with output_rule():
            check_plot_targets(plots, overwrite, [trace])
    loaded, config, non_finite = _trace_and_config(trace)
    note = (err.print if as_json else out.print)
    if non_finite:
        note(f"warning: the run's config held values that were not finite (stored as null): {', '.join(non_finite)}; "
             f"figures that depend on them are nan", highlight=False, soft_wrap=True)
    note_recovery(loaded, note)
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
    with quiet_nan(bool(non_finite)):  # nan figures were announced above
        summaries = summarize(loaded, config)
        links = link_stats_of_trace(loaded)
        departures = departures_of_trace(loaded, config)
        if as_json:
            out.print_json(json.dumps({"trace": str(trace), "law": config.platoon.law, "status": status,
                                        **report_json(summaries, config, departures), "links": link_rows(links)}))
        else:
            reached = float(loaded.component(loaded.vehicles()[0])["t"][-1])  # a run that ended early: how far
            shown = status if status == "completed" else f"{status} at t = {reached:.6g} of {config.simulation.stop_time:g} s"
            out.print(summary_table(summaries, config, f"{trace.name}: {config.header_text()} ({shown})"))
            if links:
                from orchestrator.cli.tables import link_table

                out.print(link_table(links))
            for line in departures_lines(departures):
                out.print(line, highlight=False, soft_wrap=True)
        if plots is not None:
            from orchestrator.analysis.plots import write_plots

            with output_rule():
                written = write_plots(loaded, config, plots, overwrite, [trace])
            for path in written:
                note(f"wrote {path}")


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
    loaded, config, _ = _trace_and_config(trace, **bodies)
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
