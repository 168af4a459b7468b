"""Hand trace blocks to a second process: the stepping process only copies rows into shared memory.

Encoding a trace is expensive in Python (a JSON message per component and point costs about as much
as a few FMU-steps of our Python FMUs; docs/performance.md), so recording every step in the stepping
process slows a run down by tens of percent. ``OffloadedSink`` is a block sink for
``NativeMaster.run_blocks`` that copies each block into one of a few shared-memory slots and sends
its row count down a pipe; a worker process (started with ``spawn``, so it never inherits the FMUs
of this interpreter) runs the real sink on it and gives the slot back. The stepping process waits
only when every slot is still being encoded (backpressure), so on a machine with a second core the
encoding costs the run almost nothing.

The real sink is built in the worker by ``factory(*args)``: a picklable callable returning an object
with ``__call__(rows)`` and, optionally, ``finish()``. A failure in the worker is reported by
``close()`` (and by the next block handed over) as ``OffloadError`` with the worker's traceback.
"""

from __future__ import annotations

import multiprocessing
import traceback
from multiprocessing import shared_memory
from typing import Any, Callable

import numpy as np


class OffloadError(RuntimeError):
    """The worker process failed; the message holds its traceback."""


def _worker(connection, name: str, shape: tuple[int, int, int], factory: Callable[..., Any], args: tuple) -> None:
    memory = shared_memory.SharedMemory(name=name)
    try:
        slots = np.ndarray(shape, dtype=np.float64, buffer=memory.buf)
        try:
            sink = factory(*args)
            connection.send(("ready", None))
            while True:
                message = connection.recv()
                if message is None:
                    break
                slot, rows = message
                sink(slots[slot, :rows])
                connection.send(("free", slot))
            finish = getattr(sink, "finish", None)
            if finish is not None:
                finish()
            connection.send(("done", None))
        except BaseException:
            connection.send(("error", traceback.format_exc()))
        finally:
            del slots
    finally:
        memory.close()


class OffloadedSink:
    """A ``run_blocks`` sink that runs ``factory(*args)`` in a worker process on shared-memory blocks."""

    def __init__(self, factory: Callable[..., Any], args: tuple, width: int, block: int, slots: int = 3) -> None:
        self.width, self.block = width, block
        self._memory = shared_memory.SharedMemory(create=True, size=max(1, slots * block * width * 8))
        self._slots = np.ndarray((slots, block, width), dtype=np.float64, buffer=self._memory.buf)
        self._free = list(range(slots))
        context = multiprocessing.get_context("spawn")
        self._connection, child = context.Pipe()
        self._process = context.Process(target=_worker, args=(child, self._memory.name, (slots, block, width), factory, args),
                                        daemon=True)
        self._process.start()
        child.close()
        self._closed = False
        self._done = False
        self.blocks = 0
        self.waits = 0  # blocks that had to wait for a free slot
        self._receive()  # "ready": the worker is up and its sink is built (or its error)

    def _receive(self) -> None:
        try:
            kind, value = self._connection.recv()
        except EOFError:  # the worker died without a word (killed, crashed)
            self._process.join(timeout=5)
            self._fail(f"the worker process ended with exit code {self._process.exitcode}")
        if kind == "free":
            self._free.append(value)
        elif kind == "error":
            self._fail(value)
        elif kind == "done":
            self._done = True
        elif kind != "ready":
            self._fail(f"unexpected message {kind!r}")

    def _fail(self, text: str) -> None:
        self._closed = True
        self._process.join(timeout=5)
        self._release()
        raise OffloadError(f"trace worker failed:\n{text}")

    def __call__(self, rows: np.ndarray) -> None:
        if self._closed:
            raise OffloadError("the sink is closed")
        start = 0
        while start < len(rows):
            while self._connection.poll():  # collect slots given back, without waiting
                self._receive()
            if not self._free:
                self.waits += 1
                self._receive()
                continue
            slot = self._free.pop()
            count = min(self.block, len(rows) - start)
            self._slots[slot, :count] = rows[start:start + count]
            self._connection.send((slot, count))
            self.blocks += 1
            start += count

    def close(self) -> None:
        """Wait until the worker encoded every block and finished its sink; raise if it failed."""
        if self._closed:
            return
        try:
            self._connection.send(None)
            while not self._done:
                self._receive()
        finally:
            if not self._closed:
                self._closed = True
                self._process.join(timeout=60)
                self._release()

    def _release(self) -> None:
        try:
            del self._slots
        except AttributeError:
            pass
        self._memory.close()
        self._memory.unlink()
        self._connection.close()

    def __enter__(self) -> "OffloadedSink":
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
