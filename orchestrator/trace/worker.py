"""Encode a run's trace in a second process: the stepping process only checks and ships float64 blocks.

Encoding a trace point costs about as much as stepping our Python FMUs (JSON per component, the
Foxglove scene, MCAP framing; docs/performance.md), so a trace written in the stepping process slows
every-step tracing down by 1.5-1.8x. ``TraceWorker`` has ``TraceWriter``'s interface (``record``,
``write_block``, ``log``, ``metadata``, ``flush``, ``close``, ``rows_recorded``, ``last_time``) but runs
the real ``TraceWriter`` in a worker process: a fresh ``python -m orchestrator.trace.serve``, which
inherits none of the FMUs loaded here and imports only what writing needs (ready in about 0.1 s), while the
stepping process loads its config and FMUs (a ``TraceProcess`` lets a run start it before anything
else: `platoon run` starts one with the command, ``prestart``). The stepping process keeps what must stay on its side:

* the non-finite check, vectorized per block, so a bad output still ends the run with
  ``ComponentError`` at the right point, and the rows before it are written;
* the decimation (``every``) and the counts that the run's final metadata reports.

Blocks, log lines and metadata go down one pipe in order, so the file is the same as one written in
process (tests/test_traces.py compares them message by message). The pipe is widened to 1 MiB where
Linux allows, which lets the worker lag by many blocks before the stepping process has to wait.

Nothing is lost when things go wrong:

* Ctrl-C reaches the whole process group; the worker ignores SIGINT and SIGTERM and finishes when
  the stepping process closes the trace (with the run's final status) after its own handling.
* If the stepping process dies without closing (SIGKILL, a crash), the worker sees the pipe close,
  writes every block it received, records the run as ``aborted``, finalizes the file and puts it in
  place (``publish``: the aside file is renamed onto the trace's path; the worker holds the
  path's lock, so no other run can take the path meanwhile).
* A signal while the stepping process waits for the worker to finish (a second Ctrl-C) ends the
  wait: the worker is killed, its file keeps its complete chunks. A stalled worker never holds a run.
* If the worker dies, the stepping process raises ``TraceWorkerError`` at its next hand-over; the
  complete chunks on disk can be recovered with ``platoon trace recover``.
"""

from __future__ import annotations

import fcntl
import os
import select
import socket
import subprocess
import time as clock
from array import array
from itertools import chain
from pathlib import Path
from typing import TYPE_CHECKING, Any, Sequence

from orchestrator.support.child_python import module_command, module_environment
from orchestrator.support.rows import RowBlock, float_buffer

from .format import CHUNK_SIZE, FLUSH_INTERVAL
from .native_rows import available as native_available
from .native_rows import first_non_finite
from .writer_base import non_finite_error

if TYPE_CHECKING:  # imported when a worker starts: multiprocessing (with pickle, tempfile) is ~5 % of a short run's imports
    from multiprocessing.connection import Connection

WORKER_BLOCK = 64  # rows per hand-over: small, so the worker's backlog when the run ends stays short
PIPE_BYTES = 1 << 20  # requested pipe capacity (Linux F_SETPIPE_SZ; /proc/sys/fs/pipe-max-size allows 1 MiB)
_F_SETPIPE_SZ = 1031
CLOSE_TIMEOUT = 600.0  # s to wait for the worker to finish encoding its backlog


class TraceWorkerError(RuntimeError):
    """The trace worker process failed or died; the message says what happened and where the file is."""


def _widen(connection: Connection) -> None:
    try:
        fcntl.fcntl(connection.fileno(), _F_SETPIPE_SZ, PIPE_BYTES)
    except OSError:  # not Linux, or above the system's limit: the default 64 KiB still works, with more waiting
        pass


class TraceProcess:
    """A trace writer process, started and waiting for its writer's arguments (``TraceWorker`` sends them).

    Created before the run needs it, it lets the worker's start-up (an interpreter, the MCAP writer,
    zstd: about 0.1 s) overlap everything the stepping process does before its first step; ``close()``
    ends an unused one. ``share(fd)`` hands the worker a descriptor it keeps open for its life, e.g. the
    trace's lock (orchestrator/trace/output.py), so the path stays locked while the worker still
    writes; it travels over a Unix socket (SCM_RIGHTS), so the worker can be started before the lock
    exists. A descriptor in flight stays open: a stepping process killed right after sharing still
    leaves the lock held.
    """

    def __init__(self) -> None:
        self.process, self.outbox, self.status, self.handles = _start_worker()
        self.shared = 0  # descriptors handed over; the worker takes them with its arguments
        self.taken = False

    def share(self, fd: int) -> None:
        """Hand the worker a duplicate of ``fd`` to hold until it exits."""
        socket.send_fds(self.handles, [b"F"], [fd])
        self.shared += 1

    def close(self, wait: bool = True) -> None:
        """End the worker if no ``TraceWorker`` took it (it sees the pipe close before any argument and
        exits); ``wait``: until it has."""
        self.handles.close()
        if self.taken:
            return
        self.taken = True
        self.outbox.close()
        if not wait:
            self.status.close()
            return
        try:
            self.process.wait(timeout=10)
        except subprocess.TimeoutExpired:
            self.process.kill()
            self.process.wait()
        self.status.close()


_prestarted: TraceProcess | None = None  # started for this process's run (prestart), not taken yet


def prestart() -> None:
    """Start the trace writer process for the run this process is about to make, before the run knows
    its config (`platoon run` does when the config's size says the run will want one:
    orchestrator/cli/trace_forecast.py). ``take_prestarted`` hands it to the run; ``discard_prestarted``
    ends it if the run did not want it. A process that exits without either leaves nothing behind:
    the worker sees its inbox close before any argument and ends."""
    global _prestarted
    if _prestarted is None:
        _prestarted = TraceProcess()


def take_prestarted() -> TraceProcess | None:
    """The prestarted worker, once (None if there is none or it was taken)."""
    global _prestarted
    process, _prestarted = _prestarted, None
    return process


def discard_prestarted() -> None:
    """End the prestarted worker if no run took it, without waiting for it to finish importing: it
    exits as soon as it sees its inbox closed."""
    process = take_prestarted()
    if process is not None:
        process.close(wait=False)


def _start_worker() -> tuple[subprocess.Popen[bytes], Connection, Connection, socket.socket]:
    """Start ``python -m orchestrator.trace.serve INBOX STATUS HANDLES``: blocks in, status out, and a Unix
    socket for the descriptors it must hold (``TraceProcess.share``)."""
    from multiprocessing.connection import Connection

    inbox_read, inbox_write = os.pipe()
    status_read, status_write = os.pipe()
    handles, worker_handles = socket.socketpair(socket.AF_UNIX, socket.SOCK_STREAM)
    passed = (inbox_read, status_write, worker_handles.fileno())
    try:
        # the worker runs this very package, never a copy in the current folder (support/child_python.py)
        process = subprocess.Popen(module_command("orchestrator.trace.serve", *map(str, passed)),
                                   pass_fds=passed, stdin=subprocess.DEVNULL, env=module_environment())
    except BaseException:
        for fd in (inbox_read, inbox_write, status_read, status_write):
            os.close(fd)
        handles.close()
        raise
    finally:
        worker_handles.close()
    os.close(inbox_read)
    os.close(status_write)
    outbox = Connection(inbox_write, readable=False)
    _widen(outbox)
    return process, outbox, Connection(status_read, writable=False), handles


class TraceWorker:
    """A ``TraceWriter`` running in a worker process; same interface, same file.

    ``foxglove`` is ``(SceneSettings, components, scene_rate)``: the worker builds the
    ``FoxgloveChannels``. ``native``: the worker encodes the rows in C (``TraceWriter``'s). The constructor creates the file (so a path that cannot be written fails
    here) and hands the worker its arguments without waiting for it. ``process``: a worker started
    earlier (default: start one now).
    """

    def __init__(
        self,
        path: Path,
        components: Sequence[tuple[str, Sequence[str]]],
        descriptions: dict[str, dict[str, str]] | None = None,
        every: int = 1,
        block: int = WORKER_BLOCK,
        foxglove: tuple[Any, ...] | None = None,
        flush_interval: float = FLUSH_INTERVAL,
        chunk_size: int = CHUNK_SIZE,
        process: TraceProcess | None = None,
        publish: Path | None = None,
        native: bool = False,
    ) -> None:
        self.path = Path(path)
        self.components = [(name, list(outputs)) for name, outputs in components]
        self.native = native and native_available()  # the worker runs this install: the same extension
        self.every = every
        self.flush_interval = flush_interval
        self.path.parent.mkdir(parents=True, exist_ok=True)
        open(self.path, "wb").close()
        width = 1 + sum(len(outputs) for _, outputs in self.components)
        self._width = width
        self._buffer = float_buffer(max(block, 1), width)
        self._capacity = max(block, 1)
        self._filled = 0
        self._count = 0
        self.recorded = 0  # rows handed to the worker
        self.last_time: float | None = None
        self._last_flush = clock.monotonic()
        self._failure: TraceWorkerError | None = None
        self._closed = False
        process = process or TraceProcess()
        if process.taken:
            raise ValueError("this trace process already serves a writer")
        process.taken = True
        self._process, self._outbox, self._status = process.process, process.outbox, process.status
        self._send(("arguments", {"path": self.path, "components": self.components, "descriptions": descriptions,
                                  "foxglove": foxglove, "flush_interval": flush_interval, "chunk_size": chunk_size,
                                  "publish": publish, "native": native, "held": process.shared}))
        process.handles.close()  # what was shared stays readable for the worker

    # --- what the worker says -------------------------------------------------------------------

    def _fail(self, text: str) -> TraceWorkerError:
        self._closed = True
        self._reap()
        for end in (self._outbox, self._status):
            try:
                end.close()
            except OSError:
                pass
        lines = [line.strip() for line in text.strip().splitlines() if line.strip()] or ["no reason given"]
        if len(lines) == 1:  # a reason the worker phrased itself (e.g. a full disk: it names the file)
            summary = f"the trace writer process failed: {lines[0]}"
            if "recover" not in lines[0]:
                summary += f"; {self.path} holds its complete chunks (`platoon trace recover {self.path}`)"
        else:  # a traceback: its last line is the exception
            summary = (f"the trace writer process failed ({lines[-1]}); {self.path} holds its complete chunks "
                       f"(`platoon trace recover {self.path}` if it is unfinished)")
        self._failure = TraceWorkerError(f"{summary}\n{text}" if len(lines) > 1 else summary)
        return self._failure

    def _read_status(self) -> tuple[str, Any]:
        try:
            return self._status.recv()
        except (EOFError, OSError):
            self._reap()
            return "error", f"the worker process ended unexpectedly (exit code {self._process.returncode})"

    def _reap(self) -> None:
        try:
            self._process.wait(timeout=10)
        except subprocess.TimeoutExpired:
            self._process.kill()
            self._process.wait()

    def _check(self) -> None:
        """Raise if the worker reported a failure (no waiting)."""
        if self._failure is not None:
            raise self._failure
        while self._status.poll():
            kind, value = self._read_status()
            if kind == "error":
                raise self._fail(value)

    def _send(self, message: tuple[str, Any]) -> None:
        self._check()
        try:
            self._outbox.send(message)
        except OSError:  # broken pipe: the worker is gone; say why if it told us
            kind, value = self._read_status()
            raise self._fail(value if kind == "error" else "the worker process ended unexpectedly") from None

    # --- TraceWriter's interface ----------------------------------------------------------------

    def record(self, time: float, outputs: Sequence[Sequence[float]]) -> None:
        """Keep the outputs at ``time`` (every ``every``-th call); ship the block when full or due."""
        if self._count % self.every == 0:
            row = array("d", (time,))
            row.extend(chain.from_iterable(outputs))
            start = self._filled * self._width
            self._buffer[start:start + self._width] = row
            self._filled += 1
            if self._filled == self._capacity or clock.monotonic() - self._last_flush >= self.flush_interval:
                self.flush()
        self._count += 1

    def write_block(self, rows: Any) -> None:
        """Ship a block of flat float64 rows ``[t, outputs...]`` (a ``RowBlock`` or a 2-D array; already
        decimated), after buffered rows."""
        self.flush()
        self._ship(RowBlock.coerce(rows))

    def _ship(self, rows: RowBlock) -> None:
        if self._failure is not None or self._closed:
            return
        bad = first_non_finite(rows.values, rows.width)
        good = rows if bad is None else rows.head(bad)
        if len(good):
            self._send(("rows", (good.width, good.tobytes())))
            self.recorded += len(good)
            self.last_time = float(good.time(-1))
        if bad is not None:
            raise non_finite_error(self.components, rows.row(bad))

    @property
    def rows_recorded(self) -> int:
        return self.recorded + self._filled

    def flush(self) -> None:
        filled, self._filled = self._filled, 0
        self._last_flush = clock.monotonic()
        if filled:
            self._ship(RowBlock(self._buffer[:filled * self._width], self._width))

    def log(self, time: float, level: str, message: str) -> None:
        if self._failure is None and not self._closed:
            self._send(("call", ("log", (time, level, message))))

    def metadata(self, name: str, values: dict[str, Any]) -> None:
        if self._failure is None and not self._closed:
            self._send(("call", ("metadata", (name, values))))

    def close(self) -> None:
        """Ship what is buffered, let the worker encode its backlog and finalize the file; raise if it failed.

        A ``KeyboardInterrupt`` while waiting (the run's signal handler raises one for a signal that
        arrives while the trace is being finalized) ends the wait: the worker is killed, its file keeps
        every complete chunk (recoverable), and the interrupt propagates. A stalled worker never
        holds a run hostage.
        """
        if self._closed:
            return  # a failure was raised where it was found
        try:
            try:
                self.flush()
            finally:
                self._finish()
        except KeyboardInterrupt:
            self._process.kill()
            self._fail("interrupted while the trace writer process was finishing the file; it was stopped")
            raise

    def stalled(self, grace: float) -> bool:
        """True when the worker has taken no data for ``grace`` seconds while its pipe is full: it stopped
        reading (stopped, stuck on its disk). A send would then block for as long as it stays stalled."""
        if self._closed or self._failure is not None:
            return False
        _, writable, _ = select.select([], [self._outbox.fileno()], [], grace)
        return not writable

    def abandon(self, reason: str) -> None:
        """Stop the worker now (the user insisted and it is stalled): its file keeps every complete chunk."""
        if self._closed:
            return
        self._process.kill()
        self._fail(reason)

    def _finish(self) -> None:
        self._send(("close", None))
        self._closed = True
        deadline = clock.monotonic() + CLOSE_TIMEOUT
        while True:
            if not self._status.poll(max(0.0, deadline - clock.monotonic())):
                self._process.kill()
                raise self._fail(f"the worker did not finish within {CLOSE_TIMEOUT:g} s")
            kind, value = self._read_status()
            if kind == "closed":
                break
            if kind == "error":
                raise self._fail(value)
        self._reap()
        self._outbox.close()
        self._status.close()

