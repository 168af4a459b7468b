"""Writing run traces in MCAP (the format: docs/trace-format.md; the reading side: reader).

One JSON channel per component (``/platoon/<component>``: ``t`` and every output of the component by
its FMU variable name, one message per recorded communication point), the Foxglove channels of a
``FoxgloveChannels`` (orchestrator/trace/foxglove.py), and metadata; log_time and publish_time are the
simulation time in nanoseconds. Files are chunked, zstd-compressed and indexed; a chunk is closed at
least every ``flush_interval`` seconds of wall time, so a killed run loses at most that much. Channels
come in chunk groups (format.chunk_group: the bodies, the links and errors, the Foxglove view), each
group in chunks of its own, so a reader of the bodies decompresses none of the scene's bytes.

Rows are buffered and encoded in blocks, so a run's hot loop only appends the outputs to a list (or
fills a float64 block, in the native engine). This module imports neither numpy nor the config: the
trace worker process (orchestrator/trace/serve.py) runs it and should start fast.
"""

from __future__ import annotations

import json
import math
import os
import struct
import time as clock
import zlib
from pathlib import Path
from typing import TYPE_CHECKING, Any, Sequence

from mcap.records import MessageIndex

from orchestrator.support.output import rename_into_place
from orchestrator.support.rows import RowBlock

from .channel_copy import write_copy
from .chunks import ChunkPipeline, CompressedChunk, ThreadCompressors
from .encoding import ComponentMessages, LiveStream, register_mcap
from .format import BODIES, CHUNK_GROUPS, CHUNK_SIZE, FLUSH_INTERVAL, BLOCK, chunk_group
from .writer_base import NullTraceWriter, TraceWriteError, non_finite_error  # noqa: F401  (re-exported)
from .mcap_file import ChunkBuilder, McapFile
from .native_rows import REFUSED_ROW, native_encoder, row_values, rows_of

if TYPE_CHECKING:
    from .foxglove import FoxgloveChannels

class _MessageIndex(MessageIndex):
    """A MessageIndex whose ``records`` are its entries already packed (16 bytes each: log time, offset),
    as the C encoder returns them by the block (the library keeps a tuple per entry and writes them one by one)."""

    def write(self, stream) -> None:
        entries = b"".join(self.records)
        stream.start_record(_MESSAGE_INDEX_OPCODE)
        stream.write2(self.channel_id)
        stream.write4(len(entries))
        stream.write(entries)
        stream.finish_record()


_MESSAGE_INDEX_OPCODE = 0x07
_MESSAGE_OPCODE = 0x05
# a Message record's header: opcode, record length, channel id | sequence, log time, publish time
_MESSAGE_HEADER_START = struct.Struct("<BQH")
_MESSAGE_HEADER_TAIL = struct.Struct("<IQQ")
_MESSAGE_HEADER_SIZE = _MESSAGE_HEADER_START.size + _MESSAGE_HEADER_TAIL.size
_INDEX_ENTRY = struct.Struct("<QQ")
ZSTD_LEVEL = 1  # zstd's fastest regular level: 2-3x faster than the default 3 on traces, and smaller (docs/performance.md)


def _cover(holder: Any, stamp: int, first: bool) -> None:
    """Widen ``holder``'s message_start_time / message_end_time to ``stamp`` (set both for its first message)."""
    if first:
        holder.message_start_time = holder.message_end_time = stamp
    else:
        holder.message_start_time = min(holder.message_start_time, stamp)
        holder.message_end_time = max(holder.message_end_time, stamp)


class _Encoder:
    """Encodes rows into the MCAP file (trace/mcap_file.py frames the records and writes the summary)."""

    def __init__(
        self,
        path: Path,
        components: Sequence[tuple[str, Sequence[str]]],
        descriptions: dict[str, dict[str, str]] | None,
        foxglove: "FoxgloveChannels | None",
        flush_interval: float,
        chunk_size: int,
        native: bool = False,
    ) -> None:
        compressors = ThreadCompressors(ZSTD_LEVEL)
        self.path = Path(path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._file = open(self.path, "wb")
        self._writer = McapFile(self._file, chunk_size, compressors.compress)
        self._writer.start(profile="", library="platoon-cosim")
        self.messages = ComponentMessages(components, descriptions)
        self.components = self.messages.components
        self._channels = [register_mcap(self._writer, spec) for spec in self.messages.specs]
        self.foxglove = foxglove
        if foxglove is not None:
            foxglove.register(self._writer)
        write_copy(self._writer, self._writer.schemas.values(), self._writer.channels.values())  # for recovery
        self._chunk_size = chunk_size
        self._group_of: dict[int, int] = {}  # channel id -> chunk group (BODIES when absent: live streams)
        self._builders = self._group_builders()
        # full chunks compressed on a thread (orchestrator/trace/chunks.py); None: here, by the writer's thread
        self._pipeline: ChunkPipeline | None = ChunkPipeline(compressors.compressor, self._write_chunk)
        self._compress = compressors.compress
        # the C encoder for rows given as float64 values (orchestrator/trace/native_rows.py)
        self.native = native_encoder(self.messages, self._channels, foxglove, self._group_of) if native else None
        self.width = 1 + sum(len(outputs) for _, outputs in self.components)
        self.flush_interval = flush_interval
        self.recorded = 0
        self.last_time: float | None = None
        self._last_chunk = clock.monotonic()

    def _write(self, channel: int, stamp: int, data: bytes) -> None:
        self._add(stamp, self.recorded, ((channel, data),))

    def _add(self, stamp: int, sequence: int, messages: Sequence[tuple[int, bytes]]) -> None:
        """Add messages that share one log time (= publish time) and sequence number, each to its chunk
        group's open chunk, framed here as ``mcap.records.Message`` frames itself (without an object each:
        ``Message.write`` costs about as much per message as encoding its JSON)."""
        statistics = self._writer.statistics
        counts, group_of, builders = statistics.channel_message_counts, self._group_of, self._builders
        pack = _MESSAGE_HEADER_START.pack
        tail = _MESSAGE_HEADER_TAIL.pack(sequence, stamp, stamp)  # shared by the row's messages
        entry = _INDEX_ENTRY.pack
        parts: dict[int, list[bytes]] = {}  # per chunk group: its messages of the row, one write each
        positions: dict[int, int] = {}
        for channel, data in messages:
            group = group_of.get(channel, BODIES)
            part = parts.get(group)
            if part is None:
                part = parts[group] = []
                positions[group] = builders[group].size
            indexes = builders[group].message_indices
            index = indexes.get(channel)
            if index is None:
                index = indexes[channel] = _MessageIndex(channel_id=channel, records=[])
            index.records.append(entry(stamp, positions[group]))
            part += (pack(_MESSAGE_OPCODE, 22 + len(data), channel), tail, data)
            positions[group] += _MESSAGE_HEADER_SIZE + len(data)
            counts[channel] += 1
        for group, part in parts.items():
            builder = builders[group]
            builder.records.write(b"".join(part))
            _cover(builder, stamp, builder.num_messages == 0)  # the chunk's time bounds
            builder.num_messages += len(part) // 3
        _cover(statistics, stamp, statistics.message_count == 0)  # the file's
        statistics.message_count += len(messages)
        self._close_full()

    def _group_builders(self) -> list[ChunkBuilder]:
        """One chunk builder per chunk group, the file's open chunk for the bodies (whose first chunk holds
        every schema and channel registered so far, as MCAP writers write them). Another group's first chunk
        starts with the schemas and channels of its own channels: a reader going through the file in order
        meets a channel before its messages, whichever group's chunk is written first."""
        builders = [self._writer.chunk] + [ChunkBuilder() for _ in range(1, CHUNK_GROUPS)]
        schemas = self._writer.schemas
        copied: set[tuple[int, int]] = set()
        for channel in list(self._writer.channels.values()):
            group = self._group_of[channel.id] = chunk_group(channel.topic)
            if group == BODIES:
                continue
            schema = schemas.get(channel.schema_id)
            if schema is not None and (group, schema.id) not in copied:
                copied.add((group, schema.id))
                builders[group].add(schema)
            builders[group].add(channel)
        return builders

    def _close_full(self) -> None:
        """When a chunk group's open chunk is past the chunk size, close every group's (``_chunks_full``)."""
        size = self._chunk_size
        if any(builder.size > size for builder in self._builders):
            self._chunks_full()

    def _chunks_full(self) -> None:
        """A group's open chunk is full: compress every group's on the pipeline's thread, in ``_set_order``,
        and start the next ones. The groups close together and their chunks are written back to back, so
        each chunk of a group ends at the row where the others' end: a killed run's last chunks end at one
        row, as one chunk of every channel did (recovery keeps them all), and a time slice reads the same
        rows of each group."""
        if self._pipeline is not None:
            self._pipeline.submit(*self._set_order())
        else:
            self._finalize_set()

    def _set_order(self) -> list[ChunkBuilder]:
        """The groups' builders in the order their chunks are written: the bodies' last. A file cut inside
        a set (a run killed while it is written) then holds the set's bodies only if it holds the
        rest of it, so the rows recovery keeps (up to the last the components reached) have their
        errors and their scene too."""
        return self._builders[::-1]

    def _finalize_set(self) -> None:
        """Write every group's open chunk here, in ``_set_order`` (a flush, the end)."""
        for builder in self._set_order():
            if builder.num_messages:
                chunk = CompressedChunk(builder)
                chunk.compressed = self._compress(chunk.data)
                chunk.crc = zlib.crc32(chunk.data)
                self._write_chunk(chunk)

    def _write_chunk(self, chunk: CompressedChunk) -> None:
        """Write a compressed chunk (the pipeline's, or one of ``_finalize_set``'s) with its message indexes."""
        assert chunk.compressed is not None
        self._writer.write_chunk(chunk.data, chunk.compressed, chunk.crc, chunk.message_indices,
                                 chunk.message_start_time, chunk.message_end_time)

    def _drain(self) -> None:
        """Write the chunks still being compressed: before anything else goes to the file."""
        if self._pipeline is not None:
            self._pipeline.drain()

    def float_rows(self, data: Any) -> tuple[int, float | None, int | None, int]:
        """Write rows of float64 values (``data``: a C-contiguous array or raw bytes, ``width`` per row) with
        the C encoder; close chunks as they fill. Returns (rows written, time of the last, the row it
        refused or None, why: ``native_rows.REFUSED_ROW`` or ``REFUSED_ERRORS``)."""
        statistics, builders = self._writer.statistics, self._builders
        encode = self.native.encode
        total = memoryview(data).nbytes // (8 * self.width)
        row, written_here, last_time = 0, 0, None
        while row < total:
            row, groups, time, written, indexes, refused = encode(
                data, row, [builder.size for builder in builders], self._chunk_size, self.recorded)
            if written:
                for builder, (records, least, greatest, count) in zip(builders, groups):
                    if count:
                        builder.records.write(records)
                        _cover(builder, least, builder.num_messages == 0)
                        _cover(builder, greatest, False)
                        builder.num_messages += count
                        _cover(statistics, least, statistics.message_count == 0)
                        _cover(statistics, greatest, False)
                        statistics.message_count += count
                self._indexed(indexes, statistics.channel_message_counts)
                self.recorded += written
                self.last_time = last_time = time
                written_here += written
            self._close_full()
            if refused:
                return written_here, last_time, row, refused
        self.tick()
        return written_here, last_time, None, 0

    def _indexed(self, indexes: Sequence[tuple[int, bytes, int]], counts: dict[int, int]) -> None:
        """The C encoder's message index entries, each channel's into its group's open chunk."""
        group_of, builders = self._group_of, self._builders
        for channel, entries, count in indexes:
            chunk = builders[group_of.get(channel, BODIES)].message_indices
            index = chunk.get(channel)
            if index is None:
                index = chunk[channel] = _MessageIndex(channel_id=channel, records=[])
            index.records.append(entries)
            counts[channel] += count

    def rows(self, rows: Sequence[Sequence[float]]) -> None:
        """Write flat rows ``[t, outputs of component 0, ...]`` (all finite); close the chunk if due."""
        channels, foxglove = self._channels, self.foxglove
        encode, split = self.messages.encode, self.messages.outputs
        for row in rows:
            time = row[0]
            stamp = int(round(time * 1e9))
            messages = list(zip(channels, encode(row)))
            if foxglove is not None:
                messages.extend(foxglove.row(time, stamp, split(row)))
            self._add(stamp, self.recorded, messages)
            self.recorded += 1
            self.last_time = time
        self.tick()

    def tick(self) -> None:
        """Every ``flush_interval`` of wall time: every group's open chunk written and the file flushed."""
        now = clock.monotonic()
        if now - self._last_chunk >= self.flush_interval:
            self._drain()
            self._finalize_set()
            self._file.flush()
            self._last_chunk = now

    def log(self, time: float, level: str, message: str) -> None:
        if self.foxglove is not None:
            self.foxglove.log(self._write, time, level, message)

    def live_channel(self, stream: LiveStream) -> int:
        """Register a live link's raw message channel (``LiveStream``); returns its channel id."""
        self._drain()  # the file may write the open chunk: after the pending ones
        return register_mcap(self._writer, stream.spec)

    def live_message(self, channel: int, stream: LiveStream, time: float, values: Sequence[float]) -> None:
        self._write(channel, int(round(time * 1e9)), stream.encode(time, values))

    def metadata(self, name: str, values: dict[str, str]) -> None:
        self._drain()
        self._writer.add_metadata(name, values)
        self._file.flush()

    def close(self) -> None:
        try:
            self._drain()
            self._finalize_set()  # every group's open chunk, as a full set
            self._writer.finish()
        except OSError:
            self.abandon()
            raise
        finally:
            if self._pipeline is not None:
                self._pipeline.close()
        self._file.close()

    def abandon(self) -> None:
        """Close the file without finishing it (after a write failure): no more bytes are written."""
        if self._pipeline is not None:
            self._pipeline.close()  # chunks still being compressed are not written
        try:
            self._file.close()  # closes the descriptor even when flushing the buffered tail fails
        except OSError:  # the tail could not be written either; the complete chunks stay
            pass


def _write_error(path: Path, error: OSError) -> TraceWriteError:
    reason = error.strerror or str(error)
    failure = TraceWriteError(f"cannot write the trace {path}: {reason}; the complete chunks written so far are kept "
                              f"there (`platoon trace recover {path}`)")
    failure.errno = error.errno  # str() stays the sentence above
    return failure


class TraceWriter:
    """Writes a run's trace in this process.

    Two ways in: ``record(t, outputs)`` per communication point (decimated by ``every``; rows are
    buffered and encoded in blocks), and ``write_block(rows)`` for blocks of flat rows a native loop
    already decimated. Either way a row holding a non-finite output is not written: the rows before it
    are, and ``ComponentError`` names the component, the output and the time.

    ``publish``: the final path; ``path`` is then the aside file (orchestrator/trace/output.py), renamed
    onto ``publish`` once ``close`` has finalized it. If writing fails (``OSError``: a full disk ...), the
    writer raises ``TraceWriteError`` once, writes nothing more, and leaves the file where it is.
    """

    def __init__(
        self,
        path: Path,
        components: Sequence[tuple[str, Sequence[str]]],
        descriptions: dict[str, dict[str, str]] | None = None,
        every: int = 1,
        block: int = BLOCK,
        foxglove: "FoxgloveChannels | None" = None,
        flush_interval: float = FLUSH_INTERVAL,
        chunk_size: int = CHUNK_SIZE,
        publish: Path | None = None,
        native: bool = False,
    ) -> None:
        self.path = Path(path)
        self.publish = None if publish is None else Path(publish)
        self.components = [(name, list(outputs)) for name, outputs in components]
        self._broken = False
        try:
            self._encoder = _Encoder(self.path, self.components, descriptions, foxglove, flush_interval, chunk_size,
                                     native=native)
        except OSError as error:
            raise _write_error(self.path, error) from None
        self.foxglove = foxglove
        self.every = every
        self.block = block
        self.flush_interval = flush_interval
        self._count = 0
        self._rows: list[list[float]] = []
        self.recorded = 0  # rows handed to the encoder so far
        self.last_time: float | None = None  # simulation time of the last row handed over
        self._last_flush = clock.monotonic()
        self._closed = False
        self._live: dict[str, tuple[LiveStream, int]] = {}

    def record(self, time: float, outputs: Sequence[Sequence[float]]) -> None:
        """Keep the outputs at ``time`` (every ``every``-th call) for the next flush."""
        if self._count % self.every == 0:
            row = [time]
            for values in outputs:
                row.extend(values)
            rows = self._rows
            rows.append(row)
            if len(rows) >= self.block or clock.monotonic() - self._last_flush >= self.flush_interval:
                self.flush()
        self._count += 1

    @property
    def native(self) -> bool:
        """True when float64 rows are encoded in C (``native=True`` and the extension built)."""
        return self._encoder.native is not None

    def write_block(self, rows: Any) -> None:
        """Write a block of flat float64 rows ``[t, outputs...]`` (a ``RowBlock`` or a 2-D array), already decimated."""
        block = RowBlock.coerce(rows)
        if self.native:
            self.write_floats(block.values)
        else:
            self.write_rows(block.tolist())

    def write_floats(self, data: Any) -> None:
        """Write flat rows ``[t, outputs...]`` given as float64 values (a C-contiguous array or raw bytes),
        encoded in C (``native``) or, without the extension, in Python; after any buffered rows."""
        self.flush()
        if not self.native:
            self.write_rows(rows_of(data, self._encoder.width))
            return
        if self._broken:
            return
        try:
            written, last_time, refused, why = self._encoder.float_rows(data)
        except OSError as error:
            self._broken = True
            raise _write_error(self.path, error) from None
        if written:
            self.recorded += written
            self.last_time = last_time
        if refused is not None:
            row = row_values(data, self._encoder.width, refused)
            if why == REFUSED_ROW:
                raise non_finite_error(self.components, row)
            raise ValueError(f"an error at t = {row[0]:g} s is not finite")  # FoxgloveChannels.errors_message's

    def write_rows(self, rows: list[list[float]]) -> None:
        """Write flat rows ``[t, outputs...]`` (already decimated) after any buffered ones."""
        self.flush()
        self._rows = rows
        self.flush()

    @property
    def rows_recorded(self) -> int:
        """Rows recorded so far, handed over or still buffered."""
        return self.recorded + len(self._rows)

    def _guarded(self, action: Any, *args: Any) -> None:
        """Run an encoder call; an OSError breaks the writer (nothing more is written) and is raised once."""
        if self._broken:
            return
        try:
            action(*args)
        except OSError as error:
            self._broken = True
            raise _write_error(self.path, error) from None

    def _deliver(self, rows: list[list[float]]) -> None:
        if rows:
            self._guarded(self._encoder.rows, rows)
            if not self._broken:
                self.recorded += len(rows)
                self.last_time = rows[-1][0]
        else:
            self._guarded(self._encoder.tick)

    def flush(self) -> None:
        """Hand the buffered rows to the encoder (up to the first non-finite one, which raises)."""
        rows, self._rows = self._rows, []
        self._last_flush = clock.monotonic()
        for index, row in enumerate(rows):
            if not math.isfinite(sum(row)):
                self._deliver(rows[:index])
                raise non_finite_error(self.components, row)
        self._deliver(rows)

    def log(self, time: float, level: str, message: str) -> None:
        """A line on ``/platoon/log`` (foxglove.Log) at simulation ``time``: Info, Warning or Error."""
        if self.foxglove is not None and not self._closed:
            self._guarded(self._encoder.log, time, level, message)

    def live(self, stream: str, time: float, fields: dict[str, float]) -> None:
        """A live link's raw message on ``/platoon/<stream>`` (e.g. ``vehicle3/pose``) at simulation ``time``;
        every message of a stream has the fields of its first (finite numbers; others are not written)."""
        if self._closed or self._broken:
            return
        entry = self._live.get(stream)
        if entry is None:
            link = LiveStream(stream, list(fields))
            entry = self._live[stream] = (link, self._encoder.live_channel(link))
        link, channel = entry
        values = [fields.get(key, math.nan) for key in link.keys]
        if math.isfinite(sum(values)):
            self._guarded(self._encoder.live_message, channel, link, time, values)

    def metadata(self, name: str, values: dict[str, Any]) -> None:
        self._guarded(self._encoder.metadata, name,
                      {k: v if isinstance(v, str) else json.dumps(v) for k, v in values.items()})

    def close(self) -> None:
        """Finalize the file (footer, indexes) and put it in place (``publish``); on a write failure the
        file stays where it is, unfinished, and ``TraceWriteError`` is raised (once)."""
        if self._closed:
            return
        self._closed = True
        try:
            self.flush()
        finally:
            if self._broken:
                self._encoder.abandon()
            else:
                self._guarded(self._encoder.close)
        if self._broken:
            return
        if self.publish is not None:
            try:  # the output rule's last step: the file synced, renamed, its folder synced (~20 ms for 32 MB here)
                rename_into_place(self.path, self.publish)
            except OSError as error:
                raise _write_error(self.path, error) from None
