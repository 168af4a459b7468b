"""A trace's JSON channels read into float64 columns, chunk by chunk, only the chunks and channels asked for.

``load`` (orchestrator/trace/reader.py) goes through here. A read is planned from the summary alone:
which chunks hold the wanted channels in the wanted time window (the chunk indexes), how many messages
each channel will give (the statistics, or for a window the message indexes of the chunks it touches),
so every column is allocated once at its final size and each value is written into it where it belongs.
Then each chunk is read and decompressed (the next two on threads of their own, ahead of the decoding:
zstd releases the GIL) and
its records walked by the C decoder (orchestrator/trace/native_decoder.c), which writes every number of
a message straight into its column; whatever it cannot read exactly as Python's json does it hands back,
and Python's json reads that. Without the C decoder (no C compiler at install time) the same plan is
decoded with orjson, message by message. The arrays are bit for bit what json.loads gives.
"""

from __future__ import annotations

import itertools
import json
import os
import struct
import zlib
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from typing import Any, Callable, Iterable, Iterator

import numpy as np

from .format import TraceError

try:
    from . import _decode  # type: ignore[attr-defined]
except ImportError:  # not built (no C compiler at install time): orjson decodes every message
    _decode = None

try:
    import orjson

    _json_loads: Callable[[bytes], Any] = orjson.loads
except ImportError:  # pragma: no cover - orjson is a dependency
    _json_loads = json.loads

MESSAGE_OPCODE = 0x05
MESSAGE_HEADER = 22  # channel id (2), sequence (4), log time (8), publish time (8)
_RECORD = struct.Struct("<BQ")
_MESSAGE = struct.Struct("<HIQQ")
_CHUNK_HEAD = struct.Struct("<QQQII")  # start, end, uncompressed size, crc, compression's length
_MESSAGE_INDEX_HEAD = struct.Struct("<BQHI")  # opcode, record length, channel id, entries' length
NO_LIMIT = (0, 2**64 - 1)


def native_available() -> bool:
    """True when the C decoder is built."""
    return _decode is not None


def flatten(record: dict[str, Any], prefix: str = "") -> dict[str, Any]:
    """A nested JSON object's leaves under dotted names (``vehicle1.path_error``), in text order."""
    flat: dict[str, Any] = {}
    for key, value in record.items():
        if isinstance(value, dict):
            flat.update(flatten(value, f"{prefix}{key}."))
        else:
            flat[prefix + key] = value
    return flat


@dataclass(eq=False)
class JsonColumns:
    """One JSON channel's columns as they fill: ``values[k, row]`` is key ``k`` of message ``row``."""

    name: str
    nested: bool  # the errors channel: nested objects, flattened to dotted keys
    capacity: int
    keys: list[str] = field(default_factory=list)
    values: np.ndarray | None = None
    times: np.ndarray | None = None
    count: int = 0
    order: int = -1  # when its first message came, among the slots (the channels' order in the file)
    skeleton: bytes | None = None  # None: every message is decoded by Python (C decoder absent or refused it)

    def start(self, first: bytes) -> None:
        """Take the keys from the channel's first message and allocate the columns."""
        record = self.record(first)
        self.keys = list(record)
        self.values = np.empty((len(self.keys), max(self.capacity, 1)), dtype=np.float64)
        self.times = np.empty(max(self.capacity, 1), dtype=np.uint64)
        self.capacity = self.times.shape[0]
        shape = _decode.skeleton(first) if _decode is not None else None
        numeric = all(type(value) in (int, float) for value in record.values())
        self.skeleton = shape[0] if shape is not None and shape[1] == len(self.keys) and numeric else None

    def record(self, data: bytes) -> dict[str, Any]:
        try:
            record = _json_loads(data)
        except ValueError:  # what orjson refuses but Python's json reads (NaN, Infinity): as before
            record = json.loads(data)
        if not isinstance(record, dict):
            raise ValueError("a JSON message that is not an object")
        return flatten(record) if self.nested else record

    def grow(self) -> None:
        capacity = 2 * self.capacity
        values = np.empty((len(self.keys), capacity), dtype=np.float64)
        values[:, :self.count] = self.values[:, :self.count]
        times = np.empty(capacity, dtype=np.uint64)
        times[:self.count] = self.times[:self.count]
        self.values, self.times, self.capacity = values, times, capacity

    def put(self, row: int, log_time: int, data: bytes) -> None:
        """Message ``data`` decoded by Python into row ``row`` (a value that is no number fails as
        numpy's float conversion fails)."""
        record = self.record(data)
        self.values[:, row] = [record[k] for k in self.keys]
        self.times[row] = log_time

    def append(self, log_time: int, data: bytes) -> None:
        if self.values is None:
            self.start(data)
            self.order = next(_first_seen)
        if self.count == self.capacity:
            self.grow()
        self.put(self.count, log_time, data)
        self.count += 1

    def target(self) -> tuple[Any, ...] | None:
        if self.values is None:
            return None
        if self.skeleton is None:  # every message handed back to Python
            return (b"", self.values, self.times, -1, self.capacity, self.count)
        return (self.skeleton, self.values, self.times, len(self.keys), self.capacity, self.count)

    def columns(self) -> dict[str, np.ndarray]:
        """Each key's values in log-time order (ties in file order), contiguous arrays of their own."""
        if self.values is None:
            return {}
        times = self.times[:self.count]
        values = self.values[:, :self.count]
        if self.count > 1 and bool((times[1:] < times[:-1]).any()):
            values = values[:, np.argsort(times, kind="stable")]
        if self.count < self.capacity // 2:  # a slice read from a longer plan: give the memory back
            values = values.copy()
        return {key: values[k] for k, key in enumerate(self.keys)}


@dataclass(eq=False)
class RawMessages:
    """A channel whose messages are kept as bytes (the protobuf log)."""

    name: str
    messages: list[tuple[int, bytes]] = field(default_factory=list)

    def append(self, log_time: int, data: bytes) -> None:
        self.messages.append((log_time, data))

    def ordered(self) -> list[tuple[int, bytes]]:
        return sorted(self.messages, key=lambda item: item[0])  # stable: ties stay in file order


Slot = JsonColumns | RawMessages
_first_seen = itertools.count()


class ChunkDecoder:
    """Decodes chunks' records into the slots of the wanted channels (``slots``: channel id -> slot)."""

    def __init__(self, slots: dict[int, Slot], window: tuple[int, int] = NO_LIMIT):
        self.by_channel = slots
        self.slots = list(dict.fromkeys(slots.values()))
        index = {id(slot): k for k, slot in enumerate(self.slots)}
        self.slot_of = [-1] * (max(slots, default=-1) + 1)
        for channel, slot in slots.items():
            self.slot_of[channel] = index[id(slot)]
        self.window = window

    def message(self, channel: int, log_time: int, data: bytes) -> None:
        """One message read outside chunks (or by the Python decoder)."""
        slot = self.by_channel.get(channel)
        if slot is not None and self.window[0] <= log_time <= self.window[1]:
            slot.append(log_time, bytes(data))

    def chunk(self, records: bytes) -> None:
        if _decode is None:
            for channel, log_time, data in python_messages(records):
                self.message(channel, log_time, data)
            return
        offset = 0
        while True:
            targets = [slot.target() if isinstance(slot, JsonColumns) else "raw" for slot in self.slots]
            stop, at, stopped, counts, handbacks = _decode.decode(records, offset, self.slot_of, targets, *self.window)
            for slot, count in zip(self.slots, counts):
                if isinstance(slot, JsonColumns) and slot.values is not None:
                    slot.count = count
            view = memoryview(records)
            for index, row, log_time, start, length in handbacks:
                slot = self.slots[index]
                data = bytes(view[start:start + length])
                if isinstance(slot, RawMessages):
                    slot.append(log_time, data)
                else:
                    slot.put(row, log_time, data)
            if stop == 0:
                return
            if stop == 3:
                raise TraceError(f"a damaged record at byte {at} of a chunk")
            slot = self.slots[stopped]
            _, length = _RECORD.unpack_from(records, at)
            channel, _, log_time, _ = _MESSAGE.unpack_from(records, at + 9)
            data = bytes(memoryview(records)[at + 9 + MESSAGE_HEADER:at + 9 + length])
            slot.append(log_time, data)  # its first message (keys, columns), or one that needs more room
            offset = at + 9 + length


def python_messages(records: bytes) -> Iterator[tuple[int, int, memoryview]]:
    """(channel id, log time, data) of each Message record of a chunk's records."""
    view = memoryview(records)
    at, end = 0, len(records)
    while at < end:
        if end - at < 9:
            raise TraceError(f"a damaged record at byte {at} of a chunk")
        opcode, length = _RECORD.unpack_from(records, at)
        body = at + 9
        if length > end - body:
            raise TraceError(f"a damaged record at byte {at} of a chunk")
        if opcode == MESSAGE_OPCODE:
            channel, _, log_time, _ = _MESSAGE.unpack_from(records, body)
            yield channel, log_time, view[body + MESSAGE_HEADER:body + length]
        at = body + length


def read_chunk(stream: Any, offset: int) -> bytes:
    """The decompressed records of the chunk at ``offset``, its CRC checked (``stream``: a file open for
    reading, or its descriptor: read with ``os.pread``, so threads can read one file at once)."""
    descriptor = stream if isinstance(stream, int) else stream.fileno()
    head = os.pread(descriptor, 9 + _CHUNK_HEAD.size, offset)
    if len(head) < 9 + _CHUNK_HEAD.size or head[0] != 0x06:
        raise TraceError(f"no chunk at byte {offset}")
    _, _, size, crc, compression_length = _CHUNK_HEAD.unpack_from(head, 9)
    at = offset + len(head)
    compression = os.pread(descriptor, compression_length, at).decode("utf-8", "replace")
    at += compression_length
    length_bytes = os.pread(descriptor, 8, at)
    if len(length_bytes) != 8:
        raise TraceError(f"the chunk at byte {offset} is cut short")
    (data_length,) = struct.unpack("<Q", length_bytes)
    data = os.pread(descriptor, data_length, at + 8)
    if len(data) != data_length:
        raise TraceError(f"the chunk at byte {offset} is cut short")
    records = _decompress(data, compression, size, offset)
    if len(records) != size:
        raise TraceError(f"the chunk at byte {offset} decompresses to {len(records)} bytes, not {size}")
    if crc != 0 and zlib.crc32(records) != crc:
        raise TraceError(f"the chunk at byte {offset} fails its CRC")
    return records


def _decompress(data: bytes, compression: str, size: int, offset: int) -> bytes:
    if compression == "":
        return data
    try:
        if compression == "zstd":
            import zstandard

            return zstandard.ZstdDecompressor().decompress(data, max_output_size=size)
        if compression == "lz4":
            import lz4.frame

            return lz4.frame.decompress(data)
    except ImportError:
        pass
    except Exception as error:  # zstandard.ZstdError, lz4's RuntimeError: the bytes do not decompress
        raise TraceError(f"the chunk at byte {offset} does not decompress ({error})") from None
    raise TraceError(f"the chunk at byte {offset} is compressed with {compression!r}, which this reader lacks")


def message_counts(path: str, chunks: Iterable[Any], channels: Iterable[int]) -> dict[int, int]:
    """Per channel, the messages the given chunks hold (their message indexes: 16 bytes an entry)."""
    counts = dict.fromkeys(channels, 0)
    with open(path, "rb") as stream:
        for chunk in chunks:
            for channel, offset in chunk.message_index_offsets.items():
                if channel in counts:
                    stream.seek(offset)
                    head = stream.read(_MESSAGE_INDEX_HEAD.size)
                    if len(head) == _MESSAGE_INDEX_HEAD.size:
                        counts[channel] += _MESSAGE_INDEX_HEAD.unpack(head)[3] // 16
    return counts


READ_AHEAD = 2  # chunks read and decompressed ahead of the decoding, each on a thread of its own


def decode_chunks(path: str, offsets: list[int], decoder: ChunkDecoder,
                  progress: Callable[[int, int], None] | None = None) -> None:
    """Decode the chunks at ``offsets`` in order; the next ``READ_AHEAD`` are read and decompressed on
    threads meanwhile (zstd and zlib's CRC release the GIL: on two cores a read that only picks a few
    channels costs about what decompressing costs, shared by both)."""
    if not offsets:
        return
    with open(path, "rb") as stream, ThreadPoolExecutor(READ_AHEAD) as pool:
        descriptor = stream.fileno()
        pending = [pool.submit(read_chunk, descriptor, offset) for offset in offsets[:READ_AHEAD]]
        for k in range(len(offsets)):
            records = pending.pop(0).result()
            if k + READ_AHEAD < len(offsets):
                pending.append(pool.submit(read_chunk, descriptor, offsets[k + READ_AHEAD]))
            decoder.chunk(records)
            if progress is not None:
                progress(k + 1, len(offsets))
