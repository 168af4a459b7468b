"""The runs of a sweep: each in a process of its own, forked from a warm worker that imported what a run needs.

Why a process per run: pythonfmu FMUs embed themselves in the host interpreter, so a crash inside one
(or the heap damage its teardown can cause, orchestrator/cli/app.py: main) takes its process down. In a
process of its own, such a run is recorded as failed, with the reason, and the sweep goes on; the
process leaves with ``os._exit``.

Why a warm worker: a fresh interpreter per run paid about 0.4 s of imports before its first step, as
much as a short run's own work (docs/performance.md, "Sweeps"). ``python -m orchestrator.sweep.worker
PARENT`` (the warm worker, one per thread that runs runs: a local worker, a Dask worker's thread) imports
a run's modules once, then reads run requests, one JSON line each, on stdin. For each it forks a child
that runs it and answers ``PID n`` when it forked, ``DONE {json}`` when the child ended: its exit code
(negative: the signal that killed it) and what it wrote on stdout and stderr. The child is what a fresh
process was: a session of its own (Ctrl-C in the terminal reaches only the sweep, which stops the runs
it wants stopped, ``terminate_children``), nothing of another run in it (the worker itself never runs
one), and it leaves with ``os._exit``.

The child runs ``run_scenario`` (orchestrator/execution/run.py) with the summary ``platoon report --json`` gives
(orchestrator/analysis/metrics.py), accumulated as the rows are recorded, and prints one ``RESULT {json}`` line.
Everything dies with the sweep (Linux: PR_SET_PDEATHSIG): the warm worker with the process that started
it, a run with its warm worker, so a sweep killed with SIGKILL leaves no run behind that could still write
into its folder.

``execute`` hands a run to this thread's warm worker (started on first use) and collects its outcome; the
local executor calls it in a thread per worker, and ``remote_run`` is the same on a Dask worker,
returning the trace's bytes to the client.
"""

from __future__ import annotations

import fcntl
import json
import os
import signal
import sys
import tempfile
import threading
from pathlib import Path
from typing import Any


RESULT = "RESULT "
STDERR_TAIL = 400  # characters of a dead child's stderr kept in its error message

_running: dict[int, int] = {}  # the runs under way: thread id -> the pid of its run
_running_lock = threading.Lock()
_terminating = threading.Event()  # set by terminate_children: a child dead by SIGTERM was stopped, not failed
_warm = threading.local()  # this thread's warm worker (warm.py)


def flatten_report(report: dict[str, Any]) -> dict[str, float | str]:
    """``platoon report --json``'s per-vehicle summary as columns: vehicleN.path_offset, ..., last.*; and
    ``run.left_model``, where the run left the model ("" inside it: orchestrator/analysis/validity.py)."""
    from orchestrator.analysis.validity import LEFT_MODEL, Departure, departures_cell

    row: dict[str, float | str] = {LEFT_MODEL: departures_cell([Departure(**d) for d in
                                                                       report["validity"]["departures"]])}
    vehicles = report["vehicles"]
    for vehicle in vehicles:
        row.update({f"{vehicle['name']}.{key}": value for key, value in vehicle.items() if key != "name"})
    if vehicles:
        row.update({f"last.{key}": value for key, value in vehicles[-1].items() if key != "name"})
    return row


def _die_with_parent(parent: int) -> None:
    """Ask Linux to kill this process when its parent dies; leave at once if it already has."""
    try:
        import ctypes

        libc = ctypes.CDLL(None, use_errno=True)
        libc.prctl(1, signal.SIGKILL, 0, 0, 0)  # PR_SET_PDEATHSIG = 1
    except (OSError, AttributeError):  # not Linux: the lock in the output folder still guards the files
        pass
    if os.getppid() != parent:
        os._exit(1)


def _run(request: dict[str, Any]) -> dict[str, Any]:
    from orchestrator.scenario.config import config_from_mapping
    from orchestrator.analysis.metrics import report_json, summarize
    from orchestrator.analysis.validity import departures_of_trace
    from orchestrator.execution.run import run_scenario
    from ..trace import load

    config = config_from_mapping(request["raw"])
    trace = Path(request["trace"])
    # inline: the sweep's parallelism is across runs, a trace-writer process per run would compete for the cores;
    # summarize: the report's summary, accumulated from the rows as they are recorded (no second reading)
    result = run_scenario(config, request["text"], trace, fmu_dir=Path(request["fmu_dir"]), trace_writer="inline",
                          summarize=True)
    outcome: dict[str, Any] = {"status": result.status, "error": result.error or "", "wall_time": result.wall_time}
    if result.status == "completed":
        summaries = result.summary if result.summary is not None else summarize(load(trace), config)
        departures = result.departures if result.summary is not None else departures_of_trace(load(trace), config)
        outcome["metrics"] = flatten_report(report_json(summaries, config, departures))
    return outcome


def main() -> None:
    """The warm worker: a run's modules imported once, then a child forked per request (module docstring)."""
    from orchestrator.support.internal_entry import check_arguments

    check_arguments(sys.argv[1:], "python -m orchestrator.sweep.worker PARENT_PID < REQUESTS", __doc__, count=1,
                    fits=lambda argv: argv[0].isdigit())
    _die_with_parent(int(sys.argv[1]))
    from orchestrator.support.startup import loading_a_run

    with loading_a_run():  # what every run imports, frozen out of the collector's way (startup.py)
        from orchestrator.analysis import metrics  # noqa: F401
        from orchestrator.execution import run  # noqa: F401
        from orchestrator.scenario import config  # noqa: F401
        from orchestrator.sweep.warm import preload

        preload()
    for line in sys.stdin:
        _serve(json.loads(line))
    os._exit(0)


def _serve(request: dict[str, Any]) -> None:
    """Fork a child that runs ``request``; answer ``PID``, then ``DONE`` with how it ended."""
    with tempfile.TemporaryFile() as stdout, tempfile.TemporaryFile() as stderr:  # unlinked already: nothing left behind
        sys.stdout.flush()
        server = os.getpid()
        pid = os.fork()
        if pid == 0:
            _child(request, stdout.fileno(), stderr.fileno(), server)
        _answer("PID", pid)
        _, status = os.waitpid(pid, 0)
        stdout.seek(0)
        stderr.seek(0)
        _answer("DONE", {"returncode": os.waitstatus_to_exitcode(status), "stdout": stdout.read().decode(errors="replace"),
                         "stderr": stderr.read()[-16 * STDERR_TAIL:].decode(errors="replace")})


def _answer(word: str, value: object) -> None:
    sys.stdout.write(f"{word} {json.dumps(value)}\n")
    sys.stdout.flush()


def _child(request: dict[str, Any], stdout: int, stderr: int, server: int) -> None:
    """A forked run: a session of its own, its output in the files its warm worker reads, dead with its
    warm worker; never returns."""
    try:
        os.setsid()
        null = os.open(os.devnull, os.O_RDONLY)
        for source, target in ((null, 0), (stdout, 1), (stderr, 2)):
            os.dup2(source, target)
        _die_with_parent(server)
        try:
            outcome = _run(request)
        except Exception as error:  # a bug or a broken FMU, not a run that failed: still this run's result
            outcome = {"status": "failed", "error": f"{type(error).__name__}: {error}", "wall_time": None}
        sys.stdout.write(RESULT + json.dumps(outcome) + "\n")
        sys.stdout.flush()
        sys.stderr.flush()
    finally:
        os._exit(0)


def _death_text(returncode: int | None, stderr: str) -> str:
    how = f"killed by {signal.Signals(-returncode).name}" if returncode is not None and returncode < 0 else f"exit {returncode}"
    tail = " ".join(stderr.strip().splitlines()[-3:])[-STDERR_TAIL:]
    return f"worker process died ({how})" + (f": {tail}" if tail else "")


def execute(request: dict[str, Any], trace: Path) -> dict[str, Any]:
    """Run ``request`` in a child of this thread's warm worker, writing ``trace``; its outcome (status, error,
    wall_time, metrics)."""
    from .warm import WarmWorker

    if getattr(_warm, "worker", None) is None:
        _warm.worker = WarmWorker()
    thread = threading.get_ident()

    def started(pid: int) -> None:
        with _running_lock:
            _running[thread] = pid
            if _terminating.is_set():  # stopped while it was being forked
                os.kill(pid, signal.SIGTERM)

    try:
        returncode, stdout, stderr = _warm.worker.run({**request, "trace": str(trace)}, started)
    finally:
        with _running_lock:
            _running.pop(thread, None)
    for line in stdout.splitlines():
        if line.startswith(RESULT):
            return json.loads(line[len(RESULT):])
    if _terminating.is_set() and returncode == -signal.SIGTERM:  # ours, before the run set its handlers
        return {"status": "interrupted", "error": "stopped before the run started", "wall_time": None}
    return {"status": "failed", "error": _death_text(returncode, stderr), "wall_time": None}


def terminate_children() -> None:
    """SIGTERM to every run this process's warm workers are running: each stops at its next communication point."""
    with _running_lock:
        _terminating.set()
        for pid in _running.values():
            try:
                os.kill(pid, signal.SIGTERM)
            except ProcessLookupError:  # ended meanwhile
                pass


def close_workers() -> None:
    """Let the warm workers this process started end (each ends when its requests do)."""
    from .warm import close_all

    close_all()


def _fmus_here(fmu_dir: str) -> Path:
    """The FMUs on this (possibly remote) host: ``fmu_dir`` if the client's folder is here, else a
    per-user cache built once (a lock, since several worker processes may start together)."""
    from orchestrator.components.kinds import prepare_fmus

    wanted = Path(fmu_dir)
    folder = wanted if wanted.is_dir() else Path(tempfile.gettempdir()) / f"platoon-sweep-fmus-{os.getuid()}"
    folder.mkdir(parents=True, exist_ok=True)
    with open(folder / ".build.lock", "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        prepare_fmus(folder)
    return folder


def remote_run(request: dict[str, Any]) -> dict[str, Any]:
    """The Dask task: the run in a child process on the worker, its trace returned as bytes.

    The client writes the trace and the result into the output folder, so the workers need no access
    to it (a cluster on other machines works as well as a LocalCluster).
    """
    request = {**request, "fmu_dir": str(_fmus_here(request["fmu_dir"]))}
    with tempfile.TemporaryDirectory(prefix="platoon-sweep-") as scratch:
        trace = Path(scratch) / f"{request['id']}.mcap"
        outcome = execute(request, trace)
        outcome["trace_bytes"] = trace.read_bytes() if trace.is_file() else None
    return outcome


if __name__ == "__main__":
    main()
