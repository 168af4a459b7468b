"""``platoon sweep`` and ``platoon sweep-plot``, registered on the main
app by ``register`` (orchestrator/cli/app.py).

Exit codes as for ``platoon run``: 0 every run done and completed; 1 every run done, some failed or
invalid (their errors are in results.csv), or a Dask cluster that cannot run the tasks; 2 bad input (sweep file, base config, options, a folder in use); 130 and
143 stopped by SIGINT and SIGTERM (run the same command again to resume).
"""

from __future__ import annotations

import itertools
import os
import signal
from pathlib import Path
from typing import TYPE_CHECKING, Annotated, Any, Optional

import typer
from rich.markup import escape

from orchestrator.cli.common import Overwrite
from orchestrator.sweep.spec import SweepError

if TYPE_CHECKING:  # imported where used: registering these commands must not slow every `platoon` start
    from rich.progress import Progress

    from orchestrator.sweep.plan import Run


def _cores() -> int:
    return len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count() or 1


def _describe(run: Run) -> str:
    return " ".join(f"{key}={value}" for key, value in run.values.items())


class _Display:
    """The sweep's progress: a bar (runs done, failed, time left) on a terminal, else a line per run.
    Failed runs are always named, with their error."""

    def __init__(self, quiet: bool) -> None:
        from orchestrator.cli.common import err

        self.console = err
        self.quiet = quiet
        self.bar: Progress | None = None
        self.task: Any = None

    def started(self, total: int, done: int, failed: int, todo: int) -> None:
        if self.quiet:
            return
        earlier = f", {done} done before" if done else ""
        self.console.print(f"sweep: {total} runs{earlier}, {todo} to run", highlight=False)
        if self.console.is_terminal and todo:
            from rich.progress import BarColumn, Progress, TextColumn, TimeElapsedColumn, TimeRemainingColumn

            self.bar = Progress(TextColumn("[bold]sweep"), BarColumn(), TextColumn("{task.completed}/{task.total} runs"),
                                TextColumn("[red]{task.fields[failed]} failed"), TimeElapsedColumn(),
                                TextColumn("left"), TimeRemainingColumn(), console=self.console, transient=True)
            self.task = self.bar.add_task("sweep", total=total, completed=done, failed=failed)
            self.bar.start()

    def finished(self, run: Run, record: dict[str, Any], done: int, failed: int) -> None:
        if self.quiet:
            return
        if self.bar is not None:
            self.bar.update(self.task, completed=done, failed=failed)
        status = record["status"]
        if status != "completed":
            self.console.print(f"[red]run {run.id} {status}[/] ({escape(_describe(run))}): {escape(record['error'])}",
                               markup=True, highlight=False, soft_wrap=True)
        elif self.bar is None:
            wall = record["wall_time"]
            self.console.print(f"run {run.id} completed ({escape(_describe(run))}) in {wall:.2f} s  [{done} done]",
                               markup=True, highlight=False, soft_wrap=True)

    def close(self) -> None:
        if self.bar is not None:
            self.bar.stop()


def sweep(
    sweep_file: Annotated[Path, typer.Argument(help="sweep TOML: base, and set, grid and random tables (docs/sweeps.md)")],
    out_dir: Annotated[Path, typer.Option("--out", help="folder for the traces and results.csv (resumes what it holds)")],
    workers: Annotated[Optional[int], typer.Option("--workers", min=1, help="runs at a time on this machine (default: its cores)")] = None,
    scheduler: Annotated[Optional[str], typer.Option("--scheduler", metavar="ADDRESS", help="run on an existing Dask cluster, e.g. tcp://10.0.0.5:8786")] = None,
    retry_failed: Annotated[bool, typer.Option("--retry-failed", help="run again the runs recorded as failed (or invalid)")] = False,
    allow_full_disk: Annotated[bool, typer.Option("--allow-full-disk", help="start even if the runs' traces and results are estimated not to fit on the disk (the sweep stops when it is full, the runs done kept)")] = False,
    quiet: Annotated[bool, typer.Option("--quiet", "-q", help="no progress, only failures and the final line")] = False,
) -> None:
    """Run a parameter sweep (a grid and/or random samples over a base config); stop and resume at will."""
    from fmus.builders import DEFAULT_OUT

    from orchestrator.components.kinds import prepare_fmus

    from orchestrator.cli.common import fail, out, output_rule
    from orchestrator.support.output import check_folder
    from orchestrator.sweep.executors import DaskExecutor, Executor, LocalExecutor, SweepAborted
    from orchestrator.sweep.plan import count, runs as plan_runs, value_columns
    from orchestrator.sweep.runner import run_sweep
    from orchestrator.sweep.spec import load_sweep
    from orchestrator.sweep.store import OutputFolder, check_inputs_outside

    if workers is not None and scheduler is not None:
        fail(2, "--workers and --scheduler: give one (the cluster has its own workers)")
    with output_rule():
        check_folder(out_dir, [sweep_file], "--out")
    try:  # streamed: the first point is checked here (a key no config has fails every point), the rest as they run
        spec = load_sweep(sweep_file)
        stream = plan_runs(spec)
        runs = itertools.chain([next(stream)], stream)
    except SweepError as error:
        fail(2, str(error))
    with output_rule():  # e.g. a sweep file named DIR/results.csv: the table's rebuild would replace it
        check_inputs_outside(out_dir, [sweep_file, spec.base])
    fmu_dir = DEFAULT_OUT.resolve()
    with output_rule():  # a FIFO or device where an FMU goes: one line, before any run
        prepare_fmus(fmu_dir)  # once, before the workers start (each run only checks that they are up to date)
    display = _Display(quiet)
    try:
        executor: Executor = DaskExecutor(scheduler) if scheduler is not None else LocalExecutor(workers or _cores())
        try:
            summary = run_sweep(runs, count(spec), OutputFolder(out_dir), executor, fmu_dir, display, retry_failed,
                                value_columns(spec), allow_full_disk)
        finally:
            display.close()
    except SweepError as error:
        fail(2, str(error))
    except SweepAborted as error:
        fail(1, f"sweep stopped: {error}; the runs done are kept, run the same command to resume")
    except OSError as error:  # the folder became unwritable (disk full), the cluster went away: what was committed stays
        fail(1, f"sweep stopped: {error}; the runs done are kept, run the same command to resume")
    csv_path = out_dir / "results.csv"
    if summary.signum is not None:
        name = "SIGINT (Ctrl-C)" if summary.signum == signal.SIGINT else "SIGTERM"
        fail(128 + summary.signum, f"sweep stopped by {name}: {summary.done} of {summary.total} runs done, "
                                    f"{summary.left} left ({csv_path}); run the same command to resume")
    if summary.failed:
        fail(1, f"{summary.failed} of {summary.total} runs failed or were rejected by the config (their error is in "
                 f"{csv_path}, --retry-failed runs them again)")
    out.print(f"sweep done: {summary.total} runs completed ({summary.ran} now) on {executor.name}; results: {csv_path}",
              highlight=False, soft_wrap=True)


def sweep_plot(
    out_dir: Annotated[Path, typer.Argument(help="a sweep's output folder (platoon sweep --out)")],
    value: Annotated[str, typer.Option(metavar="COLUMN", help="results.csv column to map (its magnitude, log colour scale)")] = "last.path_offset",
    x: Annotated[str, typer.Option("--x", metavar="KEY", help="horizontal axis: a config key, or d_star/R")] = "d_star/R",
    y: Annotated[str, typer.Option("--y", metavar="KEY", help="vertical axis: a config key")] = "platoon.count",
    panel: Annotated[str, typer.Option(metavar="KEY", help="one panel per value of this config key")] = "platoon.law",
    png: Annotated[Optional[Path], typer.Option("--out", help="PNG file (default DIR/map.png)")] = None,
    overwrite: Overwrite = False,
) -> None:
    """Draw a sweep's results as maps: |value| over two parameters, one panel per value of a third."""
    from orchestrator.cli.common import fail, out, output_rule
    from orchestrator.sweep.plot import draw_map
    from orchestrator.sweep.results import ResultsError
    from orchestrator.sweep.store import check_not_in_folder

    target = png or out_dir / "map.png"
    try:
        with output_rule():
            check_not_in_folder(target, out_dir)  # every file of the folder it reads, not only results.csv
            path = draw_map(out_dir, value, x, y, panel, target, overwrite)
    except ResultsError as error:  # PlotError is one too
        fail(2, str(error))
    out.print(f"wrote {path}", highlight=False, soft_wrap=True)


def stability_map(
    out_dir: Annotated[Path, typer.Argument(help="the output folder of a string-stability sweep (configs/sweeps/string_stability.toml)")],
    png: Annotated[Optional[Path], typer.Option("--out", help="PNG file (default DIR/stability.png)")] = None,
    overwrite: Overwrite = False,
) -> None:
    """Map a string-stability sweep: per law, the analytic boundary over the measured gains (delay x loss)."""
    from orchestrator.cli.common import err, fail, out, output_rule
    from orchestrator.sweep.store import check_not_in_folder

    target = png or out_dir / "stability.png"
    try:  # a target among the sweep's own files is refused in its one line, before anything else is said
        with output_rule():
            check_not_in_folder(target, out_dir)
    except ValueError as error:
        fail(2, str(error))
    err.print(f"stability-map: reading {out_dir} ...", highlight=False, soft_wrap=True)  # at once: seconds of imports
    from orchestrator.observers.progress import progress
    from orchestrator.sweep.stability_map import draw_stability_map

    def shown(traces: int, total: int):  # a bar on a terminal, plain lines elsewhere: it takes a while
        err.print(f"stability-map: measuring {traces} traces of {out_dir} and computing the analytic maps "
                  f"({total} tasks) ...", highlight=False, soft_wrap=True)
        return progress(total, "stability-map", err, unit="tasks")

    try:
        with output_rule():
            path, agreement = draw_stability_map(out_dir, target, overwrite, progress=shown)
    except ValueError as error:  # a PlotError, a ResultsError, a config the analysis refuses
        fail(2, str(error))
    for line in agreement:
        out.print(line, highlight=False, soft_wrap=True)
    out.print(f"wrote {path}", highlight=False, soft_wrap=True)


def register(app: typer.Typer) -> None:
    """Add ``sweep``, ``sweep-plot`` and ``stability-map`` to ``platoon``."""
    app.command("sweep")(sweep)
    app.command("sweep-plot")(sweep_plot)
    app.command("stability-map")(stability_map)
