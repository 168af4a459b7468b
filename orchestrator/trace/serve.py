"""The trace writer process: ``python -m orchestrator.trace.serve INBOX_FD STATUS_FD HANDLES_FD``.

Started by ``orchestrator.trace.worker.TraceWorker`` (see there for why). It reads, in order, from the
inbox pipe: the writer's arguments, then blocks of rows, log lines and metadata, then "close"; it
answers on the status pipe ("closed" or "error" with a traceback). The arguments say how many
descriptors the stepping process shared on the handles socket (the trace's lock): the worker holds
them until it exits, so the trace's path stays claimed while it writes. It imports only the writer (no
numpy, no config validation), so that it is ready while the stepping process still loads its FMUs.

Rows arrive as raw float64 bytes (``width`` values per row), already checked finite and decimated by
the stepping process. If the inbox closes without "close" (the stepping process was killed), the
worker writes every row it received, records the run as ``aborted`` and finalizes the file (and puts
it in place, when its arguments name a ``publish`` path). A write failure (a full disk) is reported
as one line, not a traceback.
"""

from __future__ import annotations

import os
import signal
import socket
import sys

if __name__ == "__main__":  # before the imports below: a Ctrl-C to the process group must not stop us
    for _signum in (signal.SIGINT, signal.SIGTERM):
        signal.signal(_signum, signal.SIG_IGN)  # the stepping process decides when and how the trace ends

import traceback  # noqa: E402
from multiprocessing.connection import Connection  # noqa: E402
from typing import Any  # noqa: E402

from .writer import TraceWriteError, TraceWriter  # noqa: E402

ABORTED = "the stepping process ended without closing the trace (killed?); every point it handed over is kept"


_held: list[int] = []  # descriptors the stepping process shared (the trace's lock), open until we exit


def serve(inbox: Connection, outbox: Connection, handles: socket.socket) -> None:
    """Build the writer, then apply what arrives in order until told to close (or orphaned)."""
    try:
        try:
            kind, arguments = inbox.recv()
        except EOFError:  # the run ended before it had anything to trace (e.g. a config error)
            return
        if kind != "arguments":
            raise ValueError(f"expected the writer's arguments first, got {kind!r}")
        _hold(handles, arguments.pop("held"))
        foxglove = arguments.pop("foxglove")
        if foxglove is not None:
            from .foxglove import FoxgloveChannels

            foxglove = FoxgloveChannels(*foxglove)
        writer = TraceWriter(foxglove=foxglove, **arguments)
    except TraceWriteError as error:  # a full disk, ...: one line says it all
        outbox.send(("error", str(error)))
        return
    except BaseException:
        outbox.send(("error", traceback.format_exc()))
        return
    try:
        while True:
            try:
                kind, payload = inbox.recv()
            except EOFError:  # the stepping process is gone without closing: keep everything it sent
                abandon(writer)
                return
            if kind == "rows":
                writer.write_floats(payload[1])  # float64 bytes: encoded in C when the writer is native
            elif kind == "call":
                name, args = payload
                getattr(writer, name)(*args)
            elif kind == "close":
                writer.close()
                outbox.send(("closed", writer.recorded))
                return
            else:
                raise ValueError(f"unexpected message {kind!r}")
    except BaseException as error:
        text = str(error) if isinstance(error, TraceWriteError) else traceback.format_exc()
        try:
            writer.close()  # what was written stays readable
        except OSError:
            pass  # the file could not be finished (e.g. the disk is full): its complete chunks stay
        finally:
            try:
                outbox.send(("error", text))
            except OSError:
                pass


def _hold(handles: socket.socket, count: int) -> None:
    """Take the ``count`` descriptors shared before the arguments; keep them open for the process's life."""
    while len(_held) < count:
        _, fds, _, _ = socket.recv_fds(handles, 1, count - len(_held))
        if not fds:
            raise ValueError(f"expected {count} shared descriptors, the stepping process closed after {len(_held)}")
        _held.extend(fds)
    handles.close()


def abandon(writer: TraceWriter) -> None:
    """Finalize the file of a run whose stepping process died: say so in the log and the run record."""
    last = writer.last_time
    writer.log(last or 0.0, "Error", f"run aborted: {ABORTED}")
    record: dict[str, Any] = {"status": "aborted", "error": ABORTED, "steps_recorded": writer.rows_recorded,
                              "last_time": "" if last is None else repr(float(last))}
    writer.metadata("platoon.run", record)
    writer.close()


def main(argv: list[str]) -> int:
    from orchestrator.support.internal_entry import check_arguments

    check_arguments(argv, "python -m orchestrator.trace.serve INBOX_FD STATUS_FD HANDLES_FD", __doc__, count=3,
                    fits=lambda args: all(arg.isdigit() for arg in args))
    serve(Connection(int(argv[0]), writable=False), Connection(int(argv[1]), readable=False),
          socket.socket(fileno=int(argv[2])))
    return 0


if __name__ == "__main__":
    # The file is finished and in place (or the failure reported) by the time serve returns; the
    # interpreter's teardown would only make the stepping process wait for our exit (~0.15 s measured).
    code = main(sys.argv[1:])
    sys.stdout.flush()
    sys.stderr.flush()
    os._exit(code)
