"""The sweep's side of a warm worker (worker.py): start it, hand it one run at a time, read how the run ended.

One warm worker per thread that runs runs (a local worker's thread, a Dask worker's task thread): it runs
one run at a time, so a request and its two answers never interleave with another's. A warm worker
that died (it never should: the runs are its children) is reported as the run's death and started
again for the next run.
"""

from __future__ import annotations

import importlib
import json
import os
import subprocess
import tempfile
import threading
from typing import Any, Callable

from orchestrator.support.child_python import module_command, module_environment

# What a run imports on its way beyond the modules worker.main names (the engines, the FMUs' Python side,
# the trace writer): loaded once in the warm worker instead of in every run (tests/test_sweep.py checks
# a run's child imports nothing of the kind)
RUN_MODULES = ("numpy", "orchestrator.execution.native", "orchestrator.trace.writer", "orchestrator.trace.columns", "mcap.writer",
               "mcap.reader", "zstandard", "foxglove", "orchestrator.observers.summary", "concurrent.futures.thread")

_workers: set["WarmWorker"] = set()
_workers_lock = threading.Lock()


def preload() -> None:
    """Import ``RUN_MODULES`` and build the config models' validators (in the warm worker, before its first
    fork). The models defer that to their first use (orchestrator/scenario/config_types.py, ``defer_build``: a
    lone run builds only what it validates); here it is done once, not in every forked run."""
    for name in RUN_MODULES:
        importlib.import_module(name)
    from orchestrator.scenario.config import Config

    Config.model_rebuild(force=True)  # with the tables it holds


class WarmWorker:
    """``python -m orchestrator.sweep.worker``, started on the first run and kept for the next ones."""

    def __init__(self) -> None:
        self._process: subprocess.Popen | None = None
        self._stderr: Any = None  # the warm worker's own stderr (an import error, say): read if it dies

    def run(self, request: dict[str, Any], started: Callable[[int], None]) -> tuple[int | None, str, str]:
        """Run ``request`` in a child; ``started(pid)`` once it is forked. The child's exit code (negative:
        killed by that signal), stdout and stderr; a warm worker that died answers for its run."""
        process = self._process if self._process is not None and self._process.poll() is None else self._start()
        try:
            process.stdin.write(json.dumps(request) + "\n")
            process.stdin.flush()
            word, value = _answer(process)
            if word == "PID":
                started(value)
                word, value = _answer(process)
            if word == "DONE":
                return value["returncode"], value["stdout"], value["stderr"]
        except (OSError, ValueError):
            pass
        return self._died()

    def _start(self) -> subprocess.Popen:
        self.close()
        with _workers_lock:
            _workers.add(self)
        self._stderr = tempfile.TemporaryFile()
        # a session of its own: Ctrl-C in the terminal is the sweep's to handle, not the warm worker's
        self._process = subprocess.Popen(module_command("orchestrator.sweep.worker", str(os.getpid())),
                                         stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=self._stderr, text=True,
                                         start_new_session=True, env=module_environment())
        return self._process

    def _died(self) -> tuple[int | None, str, str]:
        process, stderr = self._process, self._stderr
        self._process = self._stderr = None
        if process is None:
            return None, "", ""
        code = process.wait()
        stderr.seek(0)
        text = stderr.read().decode(errors="replace")
        stderr.close()
        return code, "", text

    def close(self) -> None:
        """End the warm worker: it leaves when its requests end."""
        process, self._process = self._process, None
        if process is not None:
            try:
                process.stdin.close()
            except OSError:
                pass
            process.wait()
        if self._stderr is not None:
            self._stderr.close()
            self._stderr = None


def _answer(process: subprocess.Popen) -> tuple[str, Any]:
    line = process.stdout.readline()
    word, _, value = line.partition(" ")
    return word, json.loads(value)


def close_all() -> None:
    """End every warm worker of this process (the local executor, when its sweep is over)."""
    with _workers_lock:
        workers = list(_workers)
        _workers.clear()
    for worker in workers:
        worker.close()
