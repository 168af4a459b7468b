"""`platoon report` and what the trace commands share, without typer: a trace read back with its errors turned
into one line, its stored config, the note on a recovered trace.

The console script runs a plainly well-formed `platoon report TRACE` without typer (orchestrator/cli/launch.py),
as it runs `platoon run`: typer, its parameter adapters and the other commands' modules were about a third
of the command (docs/performance.md, "Start-up"). orchestrator/cli/trace.py declares the command for typer
and calls ``report_command``; orchestrator/cli/common.py re-exports the helpers.
"""

from __future__ import annotations

import json
import math
import threading
import warnings
from contextlib import contextmanager
from pathlib import Path
from typing import TYPE_CHECKING, Any, Iterator, Optional

from orchestrator.cli.plain import console, fail, output_rule
from orchestrator.cli.tables import summary_table
from orchestrator.scenario.raw_config import ConfigError
from orchestrator.scenario.config_text import header_text

if TYPE_CHECKING:
    from orchestrator.analysis.stored_summary import StoredSummary
    from orchestrator.scenario.config import Config


@contextmanager
def quiet_nan(quiet: bool) -> Iterator[None]:
    """Silence numpy's invalid-value warnings when a config's non-finite values make figures nan on purpose."""
    if not quiet:
        yield
        return
    import numpy as np

    with np.errstate(all="ignore"), warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        yield


def note_recovery(loaded, note) -> None:
    """A trace written by `platoon trace recover` with damaged stretches skipped: say which time is missing."""
    record = loaded.metadata.get("platoon.recovery")
    if not record or record.get("damaged", "0") == "0":
        return
    from orchestrator.trace.recovery import describe_lost

    lost = [tuple(pair) for pair in json.loads(record.get("lost", "[]"))]
    note(f"warning: recovered from a damaged trace; data is missing between {describe_lost(lost)}",
         highlight=False, soft_wrap=True)


def load_trace(trace: Path, stop: threading.Event | None = None, **selection):
    """The trace read back (``selection``: ``load``'s components, start, end, errors), with a progress bar
    or lines on stderr when reading takes more than a second; exit 2 with one line when it cannot be read.
    ``stop``, once set, interrupts the reading at its next chunk, as Ctrl-C would (``_Reading``)."""
    from orchestrator.observers.progress import late_progress
    from orchestrator.trace import TraceError, load

    if not trace.is_file():
        fail(2, f"trace {trace}: no such file")
    try:
        with late_progress(f"reading {trace.name}", lambda: console(stderr=True), "chunks") as shown:
            return load(trace, progress=shown if stop is None else _stoppable(shown, stop), **selection)
    except TraceError as error:  # says what is wrong and what to do (e.g. `platoon trace recover`)
        fail(2, f"trace {trace}: not a readable MCAP trace: {error}")
    except Exception as error:  # any other reader failure means the file is not a usable trace
        fail(2, f"trace {trace}: not a readable MCAP trace ({error}); try `platoon trace recover {trace}`")


def _stoppable(shown, stop: threading.Event):
    def tick(done: int, total: int) -> None:
        if stop.is_set():
            raise KeyboardInterrupt  # unwinds the progress bar as an interrupt in this thread would
        shown(done, total)

    return tick


class _Reading(threading.Thread):
    """``load_trace`` on a thread of its own, started before the analysis and the config models are imported:
    the chunks' decompression and decoding release the GIL, so on a second core they overlap those imports
    (reading the README's trace is about 0.09 s of CPU, the config models' import about twice that). Whatever it raises (``fail``'s SystemExit) is raised again by
    ``result``, in the command's thread, as if the trace had been read there. Used as a context: if the
    command's thread is interrupted (Ctrl-C) or fails meanwhile, the reading stops at its next chunk and its
    progress bar is taken down before the command exits, as in one thread."""

    def __init__(self, trace: Path, selection: dict[str, Any]) -> None:
        super().__init__(name="reading the trace", daemon=True)
        self.trace, self.selection = trace, selection
        self.loaded: Any = None
        self.error: BaseException | None = None
        self.stop = threading.Event()
        # what the reading imports, imported here first: the thread then imports nothing as it reads a trace
        # of ours (a progress bar after a second of reading, or another writer's lz4 chunks, import more)
        try:
            import zstandard  # noqa: F401  (the chunks' decompression)
        except ImportError:  # a trace compressed with it is then refused, by the reader, as before
            pass
        from orchestrator.observers.progress import late_progress  # noqa: F401
        from orchestrator.trace import load  # noqa: F401

        self.start()

    def run(self) -> None:
        try:
            self.loaded = load_trace(self.trace, self.stop, **self.selection)
        except BaseException as error:  # noqa: BLE001  (raised again in the command's thread)
            self.error = error

    def result(self) -> Any:
        self.join()
        if self.error is not None:
            raise self.error
        return self.loaded

    def __enter__(self) -> "_Reading":
        return self

    def __exit__(self, kind, error, traceback) -> None:
        if kind is not None:
            self.stop.set()
            self.join()


def trace_and_config(trace: Path, reading: _Reading | None = None, cached: bool = False, **selection):
    """The trace read back (``selection``: what ``load`` reads of it; or what ``reading`` read), its config and
    the keys that were not finite; exit 2 naming what is wrong. ``cached``: a config validated before may come
    back from the cache of validated configs, without pydantic (for the paths written for it: `platoon report`)."""
    loaded = reading.result() if reading is not None else load_trace(trace, **selection)
    if loaded.config is None:
        fail(2, f"trace {trace}: has no platoon.config metadata (not written by platoon run?)")
    config, non_finite = _stored_config(trace, loaded.config, cached)
    return loaded, config, non_finite


def _stored_config(trace: Path, raw: dict[str, Any], cached: bool) -> tuple[Any, list[str]]:
    """The trace's stored config and its keys that were not finite: as validated before, from the cache of
    validated configs (no pydantic: orchestrator/scenario/config_records.py), else validated and then kept when
    every value was finite (a config with nulls is rebuilt each time: scenario/stored_config.py)."""
    from orchestrator.scenario.config_records import cached_config, store_config

    found = cached_config(raw) if cached else None
    if found is not None:
        return found, []
    from orchestrator.scenario.stored_config import stored_config

    try:
        config, non_finite = stored_config(raw)
    except ConfigError as error:
        fail(2, f"trace {trace}: its stored config is not valid: {error}")
    if cached and not non_finite:
        store_config(raw, config)
    return config, non_finite


def report_command(trace: Path, as_json: bool, plots: Optional[Path], overwrite: bool) -> None:
    """`platoon report` (orchestrator/cli/trace.py declares its options): the summary of a trace, as a table
    or JSON, and the paper's panels."""
    if plots is None and report_stored(trace, as_json):
        return
    if plots is not None:  # every panel's target checked before the trace is read
        from orchestrator.analysis.plots import check_plot_targets

        with output_rule():
            check_plot_targets(plots, overwrite, [trace])
    # the recorded /platoon/errors are not read: the summary computes its errors from the bodies, as the run did
    # (half of the reading, like the 3D scene's chunks, which no reader decodes)
    from orchestrator.support.startup import loading_a_run

    # read while the modules below load, which load without garbage collection (as a run's: support/startup.py)
    with loading_a_run(), _Reading(trace, {"errors": False}) as reading:
        from orchestrator.analysis.link_stats import link_stats_of_trace
        from orchestrator.analysis.metrics import summarize
        from orchestrator.analysis.stored_summary import StoredSummary
        from orchestrator.analysis.validity import departures_of_trace

        # what prints the report, loaded while the trace is read (the reading, in C, outlasts these imports)
        console(), console(stderr=True)
        if not as_json:
            import rich.table  # noqa: F401

        # a config seen before comes back without pydantic; --plots is not written for it
        loaded, config, non_finite = trace_and_config(trace, reading, cached=plots is None)
    out, err = console(), console(stderr=True)
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
        reached = float(loaded.component(loaded.vehicles()[0])["t"][-1])  # a run that ended early: how far
        print_summary(trace, config, status, reached, StoredSummary(summaries, links, departures), as_json)
        if plots is not None:
            from orchestrator.analysis.plots import write_plots

            with output_rule():
                written = write_plots(loaded, config, plots, overwrite, [trace])
            for path in written:
                note(f"wrote {path}")


def print_summary(trace: Path, config: Config, status: str, reached: float, summary: StoredSummary,
                  as_json: bool) -> None:
    """The report's table (with the links' and the departures' lines) or its JSON, of a summary computed from
    the rows read back or stored by the run (``report_stored``): one printing for both."""
    from orchestrator.analysis.link_stats import link_rows
    from orchestrator.analysis.summary_fields import report_json

    out = console()
    if as_json:
        out.print_json(json.dumps({"trace": str(trace), "law": config.platoon.law, "status": status,
                                   **report_json(summary.vehicles, config, summary.departures),
                                   "links": link_rows(summary.links)}))
        return
    from orchestrator.analysis.validity import departures_lines

    shown = status if status == "completed" else f"{status} at t = {reached:.6g} of {config.simulation.stop_time:g} s"
    out.print(summary_table(summary.vehicles, config, f"{trace.name}: {header_text(config)} ({shown})"))
    if summary.links:
        from orchestrator.cli.tables import link_table

        out.print(link_table(summary.links))
    for line in departures_lines(summary.departures):
        out.print(line, highlight=False, soft_wrap=True)


def report_stored(trace: Path, as_json: bool) -> bool:
    """Print the summary the run stored in its trace (orchestrator/analysis/stored_summary.py) and say True;
    False, having printed nothing, wherever the rows must be read instead: no stored summary or one computed
    by other code, a run that did not complete, a recovered trace, a config with values that were not finite,
    a data section whose CRC does not check or was not recorded, anything unreadable (the full reading then
    says what is wrong, as before). Neither numpy nor the trace's decoding is loaded."""
    from orchestrator.analysis.stored_summary import RECORD, stored_summary
    from orchestrator.trace.summary_section import finished_metadata

    try:
        metadata, summary_start = finished_metadata(trace)
    except Exception:  # noqa: BLE001  (the full reading reports it, with its own words)
        return False
    found = stored_summary(metadata.get(RECORD))
    run_record, config_record = metadata.get("platoon.run", {}), metadata.get("platoon.config", {})
    if (found is None or run_record.get("status") != "completed" or "platoon.recovery" in metadata
            or "resolved" not in config_record):
        return False
    # the data section's CRC (a read of the whole file, about 10 ms for the README's trace) on a thread: reading
    # and zlib release the GIL, so on a second core it overlaps the table's imports
    verdict: list[bool | None] = []
    checking = threading.Thread(target=lambda: verdict.append(_intact(trace, summary_start)), daemon=True,
                                name="checking the trace")
    checking.start()
    try:
        if not as_json:
            import rich.table  # noqa: F401
    finally:
        checking.join()
    try:
        raw = json.loads(config_record["resolved"])
    except ValueError:
        return False
    if verdict != [True]:  # damage first: the reading names it, before anything the damage may have caused
        return False
    config, non_finite = _stored_config(trace, raw, cached=True)
    if non_finite:  # their warning and nan figures: the reading's path says them
        return False
    print_summary(trace, config, "completed", math.nan, found, as_json)
    return True


def _intact(trace: Path, summary_start: int) -> bool | None:
    """``data_section_intact``, False where the file cannot be read (the full reading then says why)."""
    from orchestrator.trace.summary_section import data_section_intact

    try:
        return data_section_intact(trace, summary_start)
    except OSError:
        return False
