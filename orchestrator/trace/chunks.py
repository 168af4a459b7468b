"""Full chunks compressed on a thread while the next chunk is encoded (the trace writer's pipeline).

zstd takes about as much CPU as encoding a trace's rows in C (docs/performance.md: "Where a traced
run's time goes"). ``zstandard`` releases the GIL while it compresses, so a second thread does it
while the writer's thread encodes the next chunk (or steps the next block, in process): on an idle
core the compression leaves the run's critical path.

Nothing about the file changes: the chunk is written by ``McapFile.write_chunk`` (trace/mcap_file.py) in
the order the chunks were filled, with its compressed bytes and CRC-32 computed here.
The writer hands over its chunk groups' full chunks together (trace/writer.py), and they are written
together, back to back: a killed run's file ends after a whole set, or inside the one being written.
At most ``PENDING`` sets wait, so memory stays bounded. The writer waits for every pending chunk
before anything else touches the file (the flush at least every ``FLUSH_INTERVAL``, metadata, a new
channel, the end), so a killed run still loses at most that interval's rows, as before; a worker
whose runner died writes everything it received, as before.
"""

from __future__ import annotations

import queue
import threading
import zlib
from collections import deque
from typing import Any, Callable

PENDING = 2  # sets of full chunks that may wait for their compression; the writer waits for the oldest beyond
_SENTINEL = None


class CompressedChunk:
    """A full chunk's records and bookkeeping, taken out of its ``ChunkBuilder`` (trace/mcap_file.py), which
    goes on empty; compressed on the thread, then written by ``McapFile.write_chunk``."""

    __slots__ = ("data", "message_indices", "message_start_time", "message_end_time", "compressed", "crc", "error",
                 "done")

    def __init__(self, builder: Any) -> None:
        self.message_indices = builder.message_indices
        self.message_start_time = builder.message_start_time
        self.message_end_time = builder.message_end_time
        self.data: bytes = builder.end()  # the records; the builder starts afresh
        self.compressed: bytes | None = None
        self.crc = 0  # CRC-32 of ``data`` (the chunk record's uncompressed_crc)
        self.error: BaseException | None = None
        self.done = threading.Event()


class ThreadCompressors:
    """zstd at one level, a compressor per thread: a ``ZstdCompressor`` used by two threads at once crashes,
    and the writer's thread and the pipeline's both compress."""

    def __init__(self, level: int) -> None:
        self._level = level
        self._local = threading.local()

    def compressor(self) -> Callable[[bytes], bytes]:
        """This thread's compress function."""
        compress = getattr(self._local, "compress", None)
        if compress is None:
            import zstandard

            compress = self._local.compress = zstandard.ZstdCompressor(level=self._level).compress
        return compress

    def compress(self, data: bytes) -> bytes:
        return self.compressor()(data)


class ChunkPipeline:
    """Compresses full chunks on one daemon thread, in order; ``write`` hands each, once compressed, to
    ``finalize`` (which writes it into the file).

    ``compressor``: makes the thread's compress function (one ``ZstdCompressor`` per thread: they are
    not thread-safe).
    """

    def __init__(self, compressor: Callable[[], Callable[[bytes], bytes]], finalize: Callable[[CompressedChunk], None]) -> None:
        self._make = compressor
        self._finalize = finalize
        self._pending: deque[list[CompressedChunk]] = deque()
        self._jobs: queue.SimpleQueue[CompressedChunk | None] = queue.SimpleQueue()
        self._thread: threading.Thread | None = None

    def submit(self, *builders: Any) -> None:
        """Take the full chunks out of ``builders`` (each goes on with an empty one; those with no message
        are left alone) and compress them, to be written together in this order; write the sets whose
        compression is done, waiting for the oldest beyond ``PENDING``."""
        chunks = [CompressedChunk(builder) for builder in builders if builder.num_messages]
        if not chunks:
            return
        if self._thread is None:
            self._thread = threading.Thread(target=self._serve, name="trace-compress", daemon=True)
            self._thread.start()
        self._pending.append(chunks)
        for chunk in chunks:
            self._jobs.put(chunk)
        self._write(keep=PENDING)

    def drain(self) -> None:
        """Write every pending chunk (waiting for its compression): before anything else goes to the file."""
        self._write(keep=0)

    def _write(self, keep: int) -> None:
        """Write the compressed sets in order, waiting for the oldest while more than ``keep`` are pending."""
        pending = self._pending
        while pending and (len(pending) > keep or all(chunk.done.is_set() for chunk in pending[0])):
            chunks = pending.popleft()
            for chunk in chunks:
                chunk.done.wait()
                if chunk.error is not None:
                    raise chunk.error
            for chunk in chunks:
                self._finalize(chunk)

    def close(self) -> None:
        """Stop the thread (pending chunks are dropped: call ``drain`` first to keep them)."""
        self._pending.clear()
        if self._thread is not None:
            self._jobs.put(_SENTINEL)
            self._thread.join()
            self._thread = None

    def _serve(self) -> None:
        compress = self._make()
        while True:
            chunk = self._jobs.get()
            if chunk is _SENTINEL:
                return
            try:
                chunk.compressed = compress(chunk.data)
                chunk.crc = zlib.crc32(chunk.data)  # the writer's thread would compute it: one pass less there
            except BaseException as error:  # e.g. MemoryError: raised by the writer's thread when it writes this chunk
                chunk.error = error
            chunk.done.set()
