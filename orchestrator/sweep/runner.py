"""The sweep loop: take the folder, submit every run not done yet, commit each one as it finishes.

Committing a run (this process only, one run at a time): its trace moves from ``<id>.mcap.part`` to
``<id>.mcap``, then its result file is written atomically (the commit), then results.csv is rebuilt.
A run the sweep stopped (outcome "interrupted") is not committed and its partial trace is removed:
the next invocation redoes it. SIGINT and SIGTERM stop the sweep this way; SIGKILL leaves the
folder in a state the next invocation cleans up (store.py).
"""

from __future__ import annotations

import itertools
import signal
import threading
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Iterable, Iterator, Protocol

from .executors import Executor, Job
from .plan import Run
from .space import check_space
from .store import OutputFolder, storing

FINISHED = ("completed", "failed", "invalid")  # statuses of a run that is done (never redone unless asked)


class Events(Protocol):
    """What the sweep tells whoever shows its progress."""

    def started(self, total: int, done: int, failed: int, todo: int) -> None: ...

    def finished(self, run: Run, record: dict[str, Any], done: int, failed: int) -> None: ...


@dataclass
class SweepSummary:
    total: int
    done: int = 0  # runs with a result (completed, failed or invalid)
    failed: int = 0  # of which failed or invalid
    ran: int = 0  # runs committed by this invocation
    signum: int | None = None  # the signal that stopped the sweep

    @property
    def left(self) -> int:
        return self.total - self.done


class _Stop:
    """SIGINT/SIGTERM handlers for the length of the sweep: remember the signal, stop the executor."""

    def __init__(self, stop: Callable[[], None]) -> None:
        self.signum: int | None = None
        self._stop = stop
        self._previous: dict[int, Any] = {}

    def _handler(self, signum: int, frame: object) -> None:
        if self.signum is None:
            self.signum = signum
            # in a thread: the handler interrupts the main thread wherever it is, possibly holding a lock
            # that stopping needs (Dask's as_completed holds its condition while the client cancels)
            threading.Thread(target=self._stop, name="sweep-stop", daemon=True).start()

    def __enter__(self) -> "_Stop":
        if threading.current_thread() is threading.main_thread():
            for signum in (signal.SIGINT, signal.SIGTERM):
                self._previous[signum] = signal.signal(signum, self._handler)
        return self

    def __exit__(self, *exc: object) -> None:
        for signum, handler in self._previous.items():
            signal.signal(signum, handler)


def _is_failure(record: dict[str, Any]) -> bool:
    return record["status"] != "completed"


def run_sweep(runs: Iterable[Run], total: int, folder: OutputFolder, executor: Executor, fmu_dir: Path, events: Events,
              retry_failed: bool = False, varied: list[str] | None = None, allow_full_disk: bool = False) -> SweepSummary:
    """Run what is not done of ``runs`` (``total`` of them, streamed: never all in memory) into ``folder``
    on ``executor``; the folder is locked throughout. ``varied``: the varied keys (the tables' columns).
    A sweep whose files would not fit on the disk is refused before its first run (space.py), unless
    ``allow_full_disk``; a sweep refused before its first run leaves the disk as it found it (``undo``)."""
    folder.acquire()
    started = False
    summary = SweepSummary(total)
    varied = varied or []
    runs = iter(runs)
    first = next(runs, None)  # the point whose files stand for every run's in the disk estimate
    runs = itertools.chain([first] if first is not None else [], runs)
    try:
        # a sweep killed between a commit and its row: the table catches up (and says what is done already)
        done, failed = folder.write_tables(varied, parquet=False)
        done, failed = (done - failed, 0) if retry_failed else (done, failed)
        check_space(folder.root, first.config if first is not None else None, total - done, allow_full_disk)
        events.started(summary.total, done, failed, total - done)

        def commit(run: Run, outcome: dict[str, Any], trace: Path | None, index: int) -> None:
            record = folder.record(run, outcome, trace, index)
            folder.append_row(record, varied)
            summary.done += 1
            summary.ran += 1
            summary.failed += _is_failure(record)
            events.finished(run, record, summary.done, summary.failed)

        started = True  # from here on runs are made: what they leave is kept
        jobs = _jobs(runs, folder, fmu_dir, summary, retry_failed, commit)
        with _Stop(executor.stop) as stop:
            for job, outcome in executor.outcomes(jobs):
                partial = job.partial_trace
                if outcome.get("trace_bytes") is not None:  # a remote run: its trace came back with it
                    with storing(partial, "write the run's trace"):
                        partial.write_bytes(outcome.pop("trace_bytes"))
                outcome.pop("trace_bytes", None)
                if outcome["status"] == "interrupted":
                    partial.unlink(missing_ok=True)
                    continue
                commit(job.run, outcome, folder.place_trace(job.run, partial) if partial.is_file() else None, job.index)
            summary.signum = stop.signum
        folder.write_tables(varied)  # once at the end: results.csv in plan order, and results.parquet
    except BaseException:
        executor.stop()  # nothing more is started; local runs under way stop (their results are dropped)
        if not started:  # refused up front: remove the folders and files this invocation made
            folder.undo()
        raise
    finally:
        executor.close()
        folder.release()
    return summary


def _jobs(runs: Iterable[Run], folder: OutputFolder, fmu_dir: Path, summary: SweepSummary, retry_failed: bool,
          commit: Callable[[Run, dict[str, Any], Path | None, int], None]) -> Iterator[Job]:
    """The runs still to do, as jobs, one at a time as the executor asks for them (a done run is counted,
    a rejected point is committed as invalid, an outdated result is forgotten on the way)."""
    for index, run in enumerate(runs):
        record = folder.result(run)
        if record is not None and not (retry_failed and _is_failure(record)):
            summary.done += 1
            summary.failed += _is_failure(record)
            continue
        folder.forget(run)  # a result and trace of an older config, or a failure to retry: never mixed with the new
        if run.config is None:  # the config rejects this point: recorded, never run
            commit(run, {"status": "invalid", "error": run.error}, None, index)
            continue
        yield Job(run, {"id": run.id, "raw": run.raw, "text": run.text, "fmu_dir": str(fmu_dir)},
                  folder.partial_trace_path(run), index)
