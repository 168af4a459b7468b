"""The sweep loop: take the folder, submit every run not done yet, commit each one as it finishes.

Committing a run (this process only, one run at a time): its trace moves from ``<id>.mcap.part`` to
``<id>.mcap``, then its result file is written atomically (the commit), then results.csv is rebuilt.
A run the sweep stopped (outcome "interrupted") is not committed and its partial trace is removed:
the next invocation redoes it. SIGINT and SIGTERM stop the sweep this way; SIGKILL leaves the
folder in a state the next invocation cleans up (store.py).
"""

from __future__ import annotations

import signal
import threading
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Protocol

from .executors import Executor, Job
from .plan import Run
from .store import OutputFolder

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


def run_sweep(runs: list[Run], folder: OutputFolder, executor: Executor, fmu_dir: Path, events: Events,
              retry_failed: bool = False) -> SweepSummary:
    """Run what is not done of ``runs`` into ``folder`` on ``executor``; the folder is locked throughout."""
    folder.acquire()
    summary = SweepSummary(len(runs))
    try:
        todo: list[Run] = []
        for run in runs:
            record = folder.result(run)
            if record is not None and not (retry_failed and _is_failure(record)):
                summary.done += 1
                summary.failed += _is_failure(record)
            else:
                todo.append(run)
        for run in todo:
            folder.forget(run)  # a result and trace of an older config, or a failure to retry: never mixed with the new
        folder.write_tables(runs)  # a sweep killed between a commit and its table: the table catches up
        events.started(summary.total, summary.done, summary.failed, len(todo))

        def commit(run: Run, outcome: dict[str, Any], trace: Path | None) -> None:
            record = folder.record(run, outcome, trace)
            folder.write_tables(runs)
            summary.done += 1
            summary.ran += 1
            summary.failed += _is_failure(record)
            events.finished(run, record, summary.done, summary.failed)

        jobs = []
        for run in todo:
            if run.config is None:  # the config rejects this point: recorded, never run
                commit(run, {"status": "invalid", "error": run.error}, None)
            else:
                jobs.append(Job(run, {"id": run.id, "raw": run.raw, "text": run.text, "fmu_dir": str(fmu_dir)},
                                folder.partial_trace_path(run)))
        with _Stop(executor.stop) as stop:
            for job, outcome in executor.outcomes(jobs):
                partial = job.partial_trace
                if outcome.get("trace_bytes") is not None:  # a remote run: its trace came back with it
                    partial.write_bytes(outcome.pop("trace_bytes"))
                outcome.pop("trace_bytes", None)
                if outcome["status"] == "interrupted":
                    partial.unlink(missing_ok=True)
                    continue
                commit(job.run, outcome, folder.place_trace(job.run, partial) if partial.is_file() else None)
            summary.signum = stop.signum
    except BaseException:
        executor.stop()  # nothing more is started; local runs under way stop (their results are dropped)
        raise
    finally:
        executor.close()
        folder.release()
    return summary
