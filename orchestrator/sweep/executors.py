"""Where a sweep's runs execute: worker processes on this machine, or an existing Dask cluster.

Both run each run in a child process (worker.py) and yield ``(job, outcome)`` as runs finish, in
any order; the runner alone writes into the output folder. ``stop()`` asks for an early end: runs not
started are dropped; local runs under way stop at their next communication point (outcome
"interrupted", redone on restart). A Dask task already running cannot be stopped from here: it
finishes on its worker and its result is dropped.
"""

from __future__ import annotations

import concurrent.futures
import threading
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Iterator, Protocol

from .plan import Run
from .spec import SweepError
from .worker import close_workers, execute, remote_run, terminate_children

CONNECT_TIMEOUT = "10s"
DASK_WINDOW = 256  # runs submitted to a cluster at a time: enough to keep a big cluster busy, never the whole plan  # to reach the scheduler of --scheduler


class SweepAborted(RuntimeError):
    """The executor cannot go on (not a run's failure): the sweep stops, its finished runs kept."""


@dataclass(frozen=True)
class Job:
    run: Run
    request: dict[str, Any]  # id, raw config, TOML text, fmu_dir (worker.py)
    partial_trace: Path  # where a local run writes its trace until it is committed
    index: int = 0  # the run's place in the plan (the tables' row order)


class Executor(Protocol):
    name: str

    def outcomes(self, jobs: Iterator[Job]) -> Iterator[tuple[Job, dict[str, Any]]]:
        """Outcomes as runs finish; ``jobs`` is taken lazily, a bounded number in flight at a time."""

    def stop(self) -> None: ...

    def close(self) -> None: ...


class LocalExecutor:
    """``workers`` runs at a time, each in its own process, on this machine."""

    def __init__(self, workers: int) -> None:
        self.name = f"{workers} local worker{'s' if workers != 1 else ''}"
        self.workers = workers
        self._futures: list[concurrent.futures.Future] = []
        self._stopping = threading.Event()

    def outcomes(self, jobs: Iterator[Job]) -> Iterator[tuple[Job, dict[str, Any]]]:
        jobs = iter(jobs)
        with concurrent.futures.ThreadPoolExecutor(self.workers, thread_name_prefix="sweep-run") as pool:
            running: dict[concurrent.futures.Future, Job] = {}
            while True:
                while len(running) < 2 * self.workers and not self._stopping.is_set():  # a bounded window
                    job = next(jobs, None)
                    if job is None:
                        break
                    running[pool.submit(self._execute, job)] = job
                self._futures = list(running)
                if not running:
                    return
                finished, _ = concurrent.futures.wait(running, return_when=concurrent.futures.FIRST_COMPLETED)
                for future in finished:
                    job = running.pop(future)
                    if not future.cancelled():
                        yield job, future.result()

    def _execute(self, job: Job) -> dict[str, Any]:
        if self._stopping.is_set():  # started after stop(): a thread may pick a job before its cancel lands
            return {"status": "interrupted", "error": "sweep stopped before the run started"}
        return execute(job.request, job.partial_trace)

    def stop(self) -> None:
        self._stopping.set()
        for future in self._futures:
            future.cancel()
        terminate_children()

    def close(self) -> None:
        close_workers()  # the warm workers of this sweep's threads


class DaskExecutor:
    """The runs as tasks of an existing Dask distributed cluster (``distributed.Client(address)``)."""

    def __init__(self, address: str) -> None:
        try:
            from distributed import Client
        except ImportError:
            raise SweepError("--scheduler needs Dask: pip install 'platoon-cosim[dask]'") from None
        try:
            self.client = Client(address, timeout=CONNECT_TIMEOUT, set_as_default=False)
        except (OSError, TimeoutError, ValueError) as error:
            raise SweepError(f"--scheduler {address}: cannot connect: {error}") from None
        self.name = f"Dask scheduler {address}"
        self.address = address
        self._futures: list[Any] = []
        self._cancelled = False

    def outcomes(self, jobs: Iterator[Job]) -> Iterator[tuple[Job, dict[str, Any]]]:
        from distributed import as_completed

        jobs = iter(jobs)
        by_key: dict[str, Job] = {}
        completed = as_completed(loop=self.client.loop, with_results=True, raise_errors=False)

        def submit() -> bool:
            job = next(jobs, None)
            if job is None:
                return False
            # pure=False: a new task each time, even for a run resubmitted after a restart
            future = self.client.submit(remote_run, job.request, pure=False, key=f"platoon-run-{job.run.id}-{id(job)}")
            by_key[future.key] = job
            self._futures.append(future)
            completed.add(future)
            return True

        window = DASK_WINDOW
        while window and submit():
            window -= 1
        for future, result in completed:
            self._futures.remove(future)
            if not self._cancelled:
                submit()  # one finished, one more in flight: the window stays full
            if future.status == "cancelled":
                continue
            if future.status == "error":  # the cluster could not run the task (a run's own failure is an outcome)
                error = result[1]  # (type, exception, traceback) with raise_errors=False
                if type(error).__name__ != "KilledWorker":  # not the run's doing: e.g. another environment
                    first = str(error).strip().splitlines()[0] if str(error).strip() else ""
                    raise SweepAborted(f"--scheduler {self.address}: the cluster could not run run {by_key[future.key].run.id}: "
                                       f"{type(error).__name__}: {first} (do its workers have this platoon-cosim installed?)")
                # its worker died while running it, more than the scheduler's allowed-failures times: maybe the run's fault
                result = {"status": "failed", "error": f"Dask: {type(error).__name__}: {error}", "wall_time": None}
            yield by_key.pop(future.key), result

    def stop(self) -> None:
        self._cancelled = True
        self.client.cancel(self._futures)

    def close(self) -> None:
        self.client.close()
