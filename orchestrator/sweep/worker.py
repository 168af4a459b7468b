"""One run of a sweep, in a fresh process: ``python -m orchestrator.sweep.worker`` (request on stdin).

Why a process per run: pythonfmu FMUs embed themselves in the host interpreter, so a crash inside one
(or the heap damage its teardown can cause, orchestrator/cli/app.py: main) takes its process down. In a
process of its own, such a run is recorded as failed, with the reason, and the sweep goes on; the
process leaves with ``os._exit``. Its start-up (about 0.4 s of imports) is small against a run.

The child runs ``run_scenario`` (orchestrator/execution/run.py) with the summary ``platoon report --json`` gives
(orchestrator/analysis/metrics.py), accumulated as the rows are recorded, and prints one ``RESULT {json}`` line. It dies
with the process that started it (Linux: PR_SET_PDEATHSIG), so a sweep killed with SIGKILL leaves no
run behind that could still write into its folder.

``execute`` starts the child and collects its outcome; the local executor calls it in a thread per
worker, and ``remote_run`` is the same on a Dask worker, returning the trace's bytes to the client.
"""

from __future__ import annotations

import fcntl
import json
import os
import signal
import subprocess
import sys
import tempfile
import threading
from pathlib import Path
from typing import Any

from orchestrator.support.child_python import module_command, module_environment

RESULT = "RESULT "
STDERR_TAIL = 400  # characters of a dead child's stderr kept in its error message

_children: set[subprocess.Popen] = set()
_children_lock = threading.Lock()
_terminating = threading.Event()  # set by terminate_children: a child dead by SIGTERM was stopped, not failed


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
    from orchestrator.support.internal_entry import check_arguments

    check_arguments(sys.argv[1:], "python -m orchestrator.sweep.worker < REQUEST.json", __doc__, count=0)
    try:
        request = json.loads(sys.stdin.read())
    except ValueError:
        sys.exit("error: python -m orchestrator.sweep.worker reads a run request (JSON) on stdin; `platoon sweep` sends it")
    _die_with_parent(request["parent"])
    try:
        outcome = _run(request)
    except Exception as error:  # a bug or a broken FMU, not a run that failed: still this run's result
        outcome = {"status": "failed", "error": f"{type(error).__name__}: {error}", "wall_time": None}
    sys.stdout.write(RESULT + json.dumps(outcome) + "\n")
    sys.stdout.flush()
    sys.stderr.flush()
    os._exit(0)


def _death_text(process: subprocess.Popen, stderr: str) -> str:
    code = process.returncode
    how = f"killed by {signal.Signals(-code).name}" if code is not None and code < 0 else f"exit {code}"
    tail = " ".join(stderr.strip().splitlines()[-3:])[-STDERR_TAIL:]
    return f"worker process died ({how})" + (f": {tail}" if tail else "")


def execute(request: dict[str, Any], trace: Path) -> dict[str, Any]:
    """Run ``request`` in a child process writing ``trace``; its outcome (status, error, wall_time, metrics).

    The child has a session of its own: Ctrl-C in the terminal reaches only the sweep, which stops
    the children it wants stopped (``terminate_children``); their outcome is "interrupted".
    """
    message = json.dumps({**request, "trace": str(trace), "parent": os.getpid()})
    process = subprocess.Popen(module_command("orchestrator.sweep.worker"), stdin=subprocess.PIPE, stdout=subprocess.PIPE,
                               stderr=subprocess.PIPE, text=True, start_new_session=True, env=module_environment())
    with _children_lock:
        _children.add(process)
    try:
        stdout, stderr = process.communicate(message)
    finally:
        with _children_lock:
            _children.discard(process)
    for line in stdout.splitlines():
        if line.startswith(RESULT):
            return json.loads(line[len(RESULT):])
    if _terminating.is_set() and process.returncode == -signal.SIGTERM:  # ours, before the run set its handlers
        return {"status": "interrupted", "error": "stopped before the run started", "wall_time": None}
    return {"status": "failed", "error": _death_text(process, stderr), "wall_time": None}


def terminate_children() -> None:
    """SIGTERM to every run this process started: each stops at its next communication point."""
    with _children_lock:
        _terminating.set()
        for process in _children:
            if process.poll() is None:
                process.terminate()


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
