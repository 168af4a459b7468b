"""The trace's MCAP file layer: records framed by the ``mcap`` package's public record classes, chunks our own.

Why a layer of our own and not ``mcap.writer.Writer``: a trace writes its channels in chunk groups
(format.chunk_group: bodies, links and errors, the Foxglove view), each group's messages in chunks of
their own, compressed on a thread (chunks.py) at our zstd level. The library's Writer keeps one chunk
open and compresses through its module's ``zstandard``; doing groups through it meant swapping its
private state. Here every record is framed by ``mcap.records``' own ``write`` methods into a
``mcap.data_stream.RecordBuilder`` (both public), and this module decides only what the Writer decides:
the order of the records, the chunk and message indexes, the statistics and the summary. It decides
them as the Writer does (its defaults: every index, repeated schemas and channels, statistics, summary
offsets, CRCs of chunks and summary, none of the data section), so a file of one chunk group with the
Writer's compressor is byte for byte the file the Writer writes (tests/test_traces.py holds the two
together); the compressor is passed in, not patched.
"""

from __future__ import annotations

import struct
import zlib
from collections import defaultdict
from typing import Any, BinaryIO, Callable

from mcap.data_stream import RecordBuilder
from mcap.opcode import Opcode
from mcap.records import (
    Channel,
    Chunk,
    ChunkIndex,
    DataEnd,
    Footer,
    Header,
    Message,
    MessageIndex,
    Metadata,
    MetadataIndex,
    Schema,
    Statistics,
    SummaryOffset,
)

MAGIC = b"\x89MCAP0\r\n"
# the footer's bytes up to its CRC field (opcode, length, summary start, summary offset start): the
# summary's CRC covers them (MCAP spec, Footer)
_FOOTER_PREFIX = struct.Struct("<BQQQ")
COMPRESSION = "zstd"  # the name a Chunk record gives its compression (the compressor is the caller's)


def framed(record: Any) -> bytes:
    """One record's bytes: opcode, length, body, as the record class frames itself."""
    builder = RecordBuilder()
    record.write(builder)
    return builder.end()


class ChunkBuilder:
    """One chunk being filled: its records so far, each channel's message index, its time bounds.

    ``records`` is public on purpose: the trace writer appends Message records it framed itself (the
    C encoder frames whole blocks of them) and reads ``records.count`` for their offsets.
    """

    __slots__ = ("records", "message_indices", "num_messages", "message_start_time", "message_end_time")

    def __init__(self) -> None:
        self.records = RecordBuilder()
        self.message_indices: dict[int, MessageIndex] = {}
        self.num_messages = 0
        self.message_start_time = 0
        self.message_end_time = 0

    @property
    def size(self) -> int:
        """Bytes of records in the chunk so far (uncompressed)."""
        return self.records.count

    def add(self, record: Schema | Channel) -> None:
        """A schema or channel record, in the chunk before the first message that uses it."""
        record.write(self.records)

    def add_message(self, message: Message) -> None:
        """A message as the library's chunk builder adds it (time bounds, index entry, record)."""
        if self.num_messages == 0:
            self.message_start_time = message.log_time
        else:
            self.message_start_time = min(self.message_start_time, message.log_time)
        self.message_end_time = max(self.message_end_time, message.log_time)
        index = self.message_indices.get(message.channel_id)
        if index is None:
            index = self.message_indices[message.channel_id] = MessageIndex(channel_id=message.channel_id, records=[])
        index.records.append((message.log_time, self.records.count))
        self.num_messages += 1
        message.write(self.records)

    def end(self) -> bytes:
        """The chunk's records; the builder starts afresh (no records, no index, no bounds)."""
        self.message_indices = {}
        self.num_messages = 0
        self.message_start_time = self.message_end_time = 0
        return self.records.end()


class McapFile:
    """An MCAP file being written: header, schemas and channels, chunks with their message indexes,
    metadata, and at ``finish`` the summary and footer.

    ``chunk``: the open chunk that schema and channel records go into as they are registered (the
    Writer puts them in its open chunk too); the caller fills it and any other ``ChunkBuilder`` with
    messages and writes them with ``write_chunk``. ``compress``: bytes -> zstd bytes, for the chunks
    this class compresses itself (``write_open_chunk``); chunks compressed elsewhere come with theirs.
    """

    def __init__(self, stream: BinaryIO, chunk_size: int, compress: Callable[[bytes], bytes]) -> None:
        self._stream = stream
        self._chunk_size = chunk_size
        self._compress = compress
        self.schemas: dict[int, Schema] = {}
        self.channels: dict[int, Channel] = {}
        self.statistics = Statistics(
            attachment_count=0, channel_count=0, channel_message_counts=defaultdict(int), chunk_count=0,
            message_count=0, metadata_count=0, message_start_time=0, message_end_time=0, schema_count=0)
        self.chunk = ChunkBuilder()
        self._chunk_indexes: list[bytes] = []  # framed: a ChunkIndex object with its offsets costs ~10x its bytes
        self._metadata_indexes: list[MetadataIndex] = []
        self._data_crc = 0  # CRC-32 of the data section so far, recorded in DataEnd (readers may check it)

    def _write_data(self, data: bytes) -> None:
        """Bytes of the data section: written, and counted into its CRC (about 0.4 ms a MB)."""
        self._data_crc = zlib.crc32(data, self._data_crc)
        self._stream.write(data)

    def start(self, profile: str = "", library: str = "") -> None:
        self._write_data(MAGIC + framed(Header(profile, library)))

    def register_schema(self, name: str, encoding: str, data: bytes) -> int:
        schema = Schema(id=len(self.schemas) + 1, data=data, encoding=encoding, name=name)
        self.schemas[schema.id] = schema
        self.statistics.schema_count += 1
        self._into_open_chunk(schema)
        return schema.id

    def register_channel(self, topic: str, message_encoding: str, schema_id: int,
                         metadata: dict[str, str] | None = None) -> int:
        channel = Channel(id=len(self.channels) + 1, topic=topic, message_encoding=message_encoding,
                          schema_id=schema_id, metadata=dict(metadata or {}))
        self.channels[channel.id] = channel
        self.statistics.channel_count += 1
        self._into_open_chunk(channel)
        return channel.id

    def _into_open_chunk(self, record: Schema | Channel) -> None:
        """Into the open chunk, which is then written if it has grown past the chunk size (as the Writer does)."""
        self.chunk.add(record)
        if self.chunk.size > self._chunk_size:
            self.write_open_chunk()

    def add_message(self, channel_id: int, log_time: int, data: bytes, publish_time: int, sequence: int = 0) -> None:
        """One message into the open chunk (the trace's rows take the framed path: trace/writer.py)."""
        statistics = self.statistics
        statistics.message_start_time = (log_time if statistics.message_count == 0
                                         else min(log_time, statistics.message_start_time))
        statistics.message_end_time = max(log_time, statistics.message_end_time)
        statistics.channel_message_counts[channel_id] += 1
        statistics.message_count += 1
        self.chunk.add_message(Message(channel_id=channel_id, log_time=log_time, data=data,
                                       publish_time=publish_time, sequence=sequence))
        if self.chunk.size > self._chunk_size:
            self.write_open_chunk()

    def add_metadata(self, name: str, data: dict[str, str]) -> None:
        offset = self._stream.tell()
        record = framed(Metadata(name=name, metadata=data))
        self._write_data(record)
        self.statistics.metadata_count += 1
        self._metadata_indexes.append(MetadataIndex(offset=offset, length=len(record), name=name))

    def write_open_chunk(self) -> None:
        """Compress and write ``chunk`` here (nothing when it holds no message)."""
        if self.chunk.num_messages:
            indexes, start, end = self.chunk.message_indices, self.chunk.message_start_time, self.chunk.message_end_time
            data = self.chunk.end()
            self.write_chunk(data, self._compress(data), zlib.crc32(data), indexes, start, end)

    def write_chunk(self, data: bytes, compressed: bytes, crc: int, message_indices: dict[int, MessageIndex],
                    start_time: int, end_time: int) -> None:
        """A Chunk record of ``data`` (its records; ``compressed`` with zstd, ``crc`` its CRC-32), then the
        message indexes of its channels; its ChunkIndex is kept for the summary."""
        self.statistics.chunk_count += 1
        chunk_start = self._stream.tell()
        chunk = framed(Chunk(compression=COMPRESSION, data=compressed, message_start_time=start_time,
                             message_end_time=end_time, uncompressed_crc=crc, uncompressed_size=len(data)))
        self._write_data(chunk)
        indexes_start = chunk_start + len(chunk)
        builder = RecordBuilder()
        offsets = {}
        for channel, index in message_indices.items():
            offsets[channel] = indexes_start + builder.count
            index.write(builder)
        indexes = builder.end()
        self._write_data(indexes)
        self._chunk_indexes.append(framed(ChunkIndex(
            message_start_time=start_time, message_end_time=end_time, chunk_start_offset=chunk_start,
            chunk_length=len(chunk), message_index_offsets=offsets, message_index_length=len(indexes),
            compression=COMPRESSION, compressed_size=len(compressed), uncompressed_size=len(data))))

    def finish(self) -> None:
        """The end of the data section, the summary (schemas, channels, statistics, chunk indexes, the
        attachment indexes' empty group, metadata indexes, the groups' offsets), footer and magic. The
        open chunk is the caller's to write first (``write_open_chunk``)."""
        self._stream.write(framed(DataEnd(self._data_crc)))
        summary_start = self._stream.tell()
        summary = RecordBuilder()
        offsets: list[SummaryOffset] = []

        def group(opcode: Opcode, records: Any) -> None:
            begin = summary.count
            for record in records:
                if isinstance(record, bytes):
                    summary.write(record)
                else:
                    record.write(summary)
            offsets.append(SummaryOffset(group_opcode=opcode, group_start=summary_start + begin,
                                         group_length=summary.count - begin))

        group(Opcode.SCHEMA, self.schemas.values())
        group(Opcode.CHANNEL, self.channels.values())
        group(Opcode.STATISTICS, [self.statistics])
        group(Opcode.CHUNK_INDEX, self._chunk_indexes)
        group(Opcode.ATTACHMENT_INDEX, [])
        group(Opcode.METADATA_INDEX, self._metadata_indexes)
        offsets_start = summary_start + summary.count
        for offset in offsets:
            offset.write(summary)
        data = summary.end()
        footer_start = 0 if not data else summary_start
        crc = zlib.crc32(_FOOTER_PREFIX.pack(Opcode.FOOTER, 8 + 8 + 4, footer_start, offsets_start), zlib.crc32(data))
        self._stream.write(data)
        self._stream.write(framed(Footer(summary_start=footer_start, summary_offset_start=offsets_start,
                                         summary_crc=crc)))
        self._stream.write(MAGIC)
