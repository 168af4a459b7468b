"""`platoon calibrate` (a live robot's physics from the traces of live runs) and `platoon compare` (a live run
against its simulation): the lab's way from a robot to a model that predicts it (docs/hil.md,
"Calibrating your robots")."""

from __future__ import annotations

import math
from pathlib import Path
from typing import Annotated, Any, Optional

import typer

from orchestrator.cli.common import err, fail, load_trace, out
from orchestrator.support.output import OVERWRITE_HELP

POOR_FIT = 2.0  # residual / the poses' own noise above which a fit does not explain the robot
SCALE = {"m/s": (1e3, "mm/s"), "s": (1e3, "ms"), "m": (1e3, "mm"), "": (1.0, "")}


def _records(traces: list[Path], partial: bool) -> list[Any]:
    from orchestrator.analysis.robot_record import RecordError, check_complete, robot_records

    records = []
    for path in traces:
        trace = load_trace(path)
        try:
            if not partial:
                check_complete(trace, str(path))
            records += robot_records(trace, path)
        except RecordError as error:
            fail(2, str(error))
    return records


def _shown(value: float, unit: str) -> str:
    factor, shown_unit = SCALE[unit]
    if not math.isfinite(value):
        return "inf"
    return f"{value * factor:.4g}{(' ' + shown_unit) if shown_unit else ''}"


def calibration_table(calibration: Any) -> Any:
    from rich.table import Table

    table = Table(title=f"robot {calibration.robot}: {calibration.seconds:.1f} s, {calibration.poses} poses "
                        f"({'; '.join(calibration.sources)})", title_justify="left")
    for column in ("parameter", "value", "95 % interval", "identified"):
        table.add_column(column)
    for e in calibration.estimates.values():
        interval = f"{_shown(e.low, e.unit)} .. {_shown(e.high, e.unit)}" if math.isfinite(e.low) else "-"
        verdict = "yes" if e.identified else f"no: {e.note}; the nominal written"
        table.add_row(e.name, _shown(e.value, e.unit), interval, verdict)
    ratio = calibration.residual / calibration.pose_noise if calibration.pose_noise > 0 else math.inf
    table.caption = (f"path residual {calibration.residual * 1e3:.2f} mm rms per axis, {ratio:.2f} x the poses' own "
                     f"noise ({calibration.pose_noise * 1e3:.2f} mm); the run's own model: "
                     f"{calibration.residual_before * 1e3:.1f} mm. Poses arrived {calibration.delivery * 1e3:.1f} ms "
                     "after their stamps (median; the run dead-reckons over that)")
    table.caption_justify = "left"
    return table


def calibration_toml(calibrations: list[Any]) -> str:
    """The ``[m3pi]`` table of one robot, or a ``[vehicles.K.m3pi]`` table per robot (K its vehicle in the trace)."""
    lines = ["# platoon calibrate: each robot's physics as its live runs showed it (docs/hil.md, \"Calibrating your",
             "# robots\"). Parameters the traces did not identify hold the model's nominal value."]
    for calibration in calibrations:
        values = calibration.values()
        vehicle = calibration.sources[0].rsplit("vehicle", 1)[-1]
        table = "m3pi" if len(calibrations) == 1 else f"vehicles.{vehicle}.m3pi"
        missing = [e.name for e in calibration.estimates.values() if not e.identified]
        lines += ["", f"# robot {calibration.robot}, from {'; '.join(calibration.sources)}"
                  + (f"; not identified: {', '.join(missing)}" if missing else ""),
                  "# as options: " + " ".join(f"--set {table}.{k}={v:.6g}" for k, v in values.items()), f"[{table}]"]
        lines += [f"{k} = {v:.6g}" for k, v in values.items()]
    return "\n".join(lines) + "\n"


def calibrate(
    traces: Annotated[list[Path], typer.Argument(metavar="TRACE...", help="traces of live runs (the robot's commands and poses)")],
    output: Annotated[Path, typer.Option("--out", metavar="ROBOT.toml", help="write the identified [m3pi] values here")],
    plots: Annotated[Optional[Path], typer.Option("--plots", metavar="DIR", help="figures: recorded against model path, "
                                                  "speed and wheel speeds, before and after calibration")] = None,
    partial: Annotated[bool, typer.Option("--partial", help="use traces of runs that ended early (recovered, failed, "
                                          "interrupted) too")] = False,
    overwrite: Annotated[bool, typer.Option("--overwrite", help=OVERWRITE_HELP)] = False,
) -> None:
    """Identify each live robot's wheel gains, motor lag, limit, dead-band, track and latencies from live runs."""
    from orchestrator.analysis.calibrate import calibrate_robot
    from orchestrator.cli.common import check_output
    from orchestrator.observers.progress import late_progress

    check_output(output, overwrite, list(traces))
    records = _records(traces, partial)
    robots: dict[int, list[Any]] = {}
    for record in records:
        robots.setdefault(record.robot, []).append(record)
    calibrations = []
    with late_progress("calibrating", err, "fits", after=2.0) as shown:
        for number, (robot, own) in enumerate(sorted(robots.items())):
            def tick(count=[0], number=number) -> None:  # one path of the fit: ~200 per robot
                count[0] += 1
                shown(number * 200 + min(count[0], 199), 200 * len(robots))
            calibrations.append(calibrate_robot(own, tick))
    for calibration in calibrations:
        out.print(calibration_table(calibration))
        if calibration.residual > POOR_FIT * calibration.pose_noise:
            err.print(f"warning: robot {calibration.robot}: the model does not explain its poses (residual "
                      f"{calibration.residual / calibration.pose_noise:.1f} x their noise): its values are suspect "
                      "(traces of different robots under one id? a robot that slipped or was touched?)",
                      highlight=False, soft_wrap=True)
    output.write_text(calibration_toml(calibrations))
    out.print(f"wrote {output}", highlight=False)
    if plots is not None:
        from orchestrator.analysis.calibration_plots import calibration_figures

        for calibration in calibrations:
            for path in calibration_figures(robots[calibration.robot], calibration, plots):
                out.print(f"wrote {path}", highlight=False)




def compare(
    run: Annotated[Path, typer.Argument(metavar="LIVE.mcap", help="a run's trace (e.g. of a live run)")],
    other: Annotated[Path, typer.Argument(metavar="SIM.mcap", help="another run's trace (e.g. the all-FMU run of the same config)")],
) -> None:
    """Path and speed differences, per vehicle, between two runs of one scenario (a live run and its simulation)."""
    from rich.table import Table

    from orchestrator.analysis.compare import SPEED_WINDOW, run_differences

    differences = run_differences(load_trace(run), load_trace(other))
    if not differences:
        fail(2, f"{run} and {other}: no vehicle recorded at common time points in both")
    table = Table(title=f"{run.name} against {other.name}", title_justify="left")
    for column in ("vehicle", "points", "path rms", "path max", "at t", "speed rms", "speed max"):
        table.add_column(column, justify="left" if column == "vehicle" else "right", no_wrap=True)
    for d in differences:
        table.add_row(d.name, str(d.points), f"{d.path_rms * 1e3:.2f} mm", f"{d.path_max * 1e3:.2f} mm",
                      f"{d.path_max_at:.2f} s", f"{d.speed_rms * 1e3:.1f} mm/s", f"{d.speed_max * 1e3:.1f} mm/s")
    table.caption = (f"path: distance between the two positions; speed: over the ground, the distance covered in "
                     f"{SPEED_WINDOW:g} s (a live vehicle's speed output is its controller's estimate)")
    table.caption_justify = "left"
    out.print(table)


def register(app: typer.Typer) -> None:
    app.command()(calibrate)
    app.command()(compare)
