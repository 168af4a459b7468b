"""Run traces in MCAP: one JSON channel per component, Foxglove channels, metadata; reader, export, recovery.

Format (docs/trace-format.md): channel ``/platoon/<component>`` (``target``, ``vehicle1`` ...), JSON
messages with a JSON Schema, one message per recorded communication point holding ``t`` and every
output of the component by its FMU variable name; log_time and publish_time are the simulation time
in nanoseconds. With a ``FoxgloveChannels`` (orchestrator/foxglove.py) the file also holds
``/platoon/errors``, ``/platoon/scene``, ``/platoon/tf`` and ``/platoon/log``. Metadata records
``platoon.config``, ``platoon.fmus``, ``platoon.tool``, ``platoon.start`` and ``platoon.run`` (status,
error, engine, master, steps_recorded, last_time). Files are chunked, zstd-compressed and indexed; a
chunk is closed at least every ``flush_interval`` seconds of wall time, so a killed run loses at most
that much, and ``recover`` rewrites the complete chunks of an unfinished file into a valid one.

Rows are buffered and encoded in blocks, so a run's hot loop only appends the outputs to a list.
"""

from __future__ import annotations

import csv
import json
import math
import struct
import time as clock
from dataclasses import dataclass, field
from itertools import chain
from pathlib import Path
from typing import TYPE_CHECKING, Any, Sequence

import numpy as np
from mcap.exceptions import McapError
from mcap.reader import make_reader
from mcap.records import Channel, Chunk, DataEnd, Footer, Message, MessageIndex, Metadata, Schema
from mcap.data_stream import RecordBuilder
from mcap.stream_reader import StreamReader, breakup_chunk
from mcap.writer import CompressionType, Writer

from .components import ComponentError

if TYPE_CHECKING:
    from .foxglove import FoxgloveChannels

CHANNEL_PREFIX = "/platoon/"
SCHEMA_ENCODING = "jsonschema"
MESSAGE_ENCODING = "json"
KIND_KEY = "platoon.kind"  # channel metadata: "component", "errors" or "foxglove"
ERRORS_TOPIC = CHANNEL_PREFIX + "errors"
LOG_TOPIC = CHANNEL_PREFIX + "log"

CHUNK_SIZE = 1 << 20  # bytes of uncompressed records per chunk, at most
FLUSH_INTERVAL = 1.0  # s of wall time: a chunk is closed and the file flushed at least this often
BLOCK = 500  # rows buffered before they are encoded
MAGIC = b"\x89MCAP0\r\n"
FOOTER_LENGTH = 1 + 8 + 8 + 8 + 4  # opcode, record length, summary start, summary offset start, crc


class TraceError(ValueError):
    """A file that is not a usable trace; the message says why and what to do."""


def channel_name(component: str) -> str:
    return CHANNEL_PREFIX + component


def _schema(component: str, outputs: Sequence[str], descriptions: dict[str, str]) -> bytes:
    properties = {"t": {"type": "number", "description": "simulation time [s]"}}
    for name in outputs:
        properties[name] = {"type": "number", "description": descriptions.get(name, name)}
    return json.dumps(
        {
            "$schema": "https://json-schema.org/draft/2020-12/schema",
            "title": f"platoon.{component}",
            "type": "object",
            "properties": properties,
            "required": ["t", *outputs],
            "additionalProperties": False,
        }
    ).encode()


try:  # orjson writes floats (Rust, ryu) several times faster than float.__repr__, same values
    import orjson

    def number_texts(values: list[float]) -> list[bytes]:
        """JSON text of each number: shortest text that reads back as exactly the same float."""
        try:
            return orjson.dumps(values)[1:-1].split(b",")
        except TypeError:  # a number type orjson does not take (e.g. numpy scalar): its float value
            return orjson.dumps([float(v) for v in values])[1:-1].split(b",")

except ImportError:  # pragma: no cover - orjson is a dependency; this keeps a bare install working

    def number_texts(values: list[float]) -> list[bytes]:
        """JSON text of each number: shortest text that reads back as exactly the same float."""
        return [float.__repr__(float(v)).encode() for v in values]


def _template(keys: Sequence[str]) -> str:
    """A %-format that, filled with the values' JSON texts, is the JSON object of ``keys`` to values."""
    return "{" + ",".join(json.dumps(key).replace("%", "%%") + ":%s" for key in keys) + "}"


class _MessageIndex(MessageIndex):
    """A MessageIndex that packs its entries in one call (the library writes them one by one)."""

    def write(self, stream) -> None:
        stream.start_record(_MESSAGE_INDEX_OPCODE)
        stream.write2(self.channel_id)
        stream.write4(len(self.records) * 16)
        stream.write(struct.pack(f"<{2 * len(self.records)}Q", *chain.from_iterable(self.records)))
        stream.finish_record()


class _PackedRecord:
    """A summary record kept as its bytes: a ChunkIndex object with its offsets dict costs ~10 KB of
    memory for a hundred channels, its record ~1 KB, and the writer keeps one per chunk until the end."""

    __slots__ = ("data",)

    def __init__(self, record: Any) -> None:
        builder = RecordBuilder()
        record.write(builder)
        self.data = builder.end()

    def write(self, stream: Any) -> None:
        stream.write(self.data)


_MESSAGE_INDEX_OPCODE = 0x07
_MESSAGE_OPCODE = 0x05
_MESSAGE_HEADER = struct.Struct("<BQHIQQ")  # opcode, record length, channel id, sequence, log time, publish time


def _fast_path(writer: Writer):
    """The open chunk of an ``mcap`` Writer, to append Message records without a Python object each.

    ``Writer.add_message`` costs about as much per message as encoding its JSON; the records written
    here are byte for byte what it writes (tests/test_traces.py compares the files), with the same
    message indexes and statistics. Relies on the writer's private chunk builder: if a future
    ``mcap`` release changes it, this returns None and the public ``add_message`` is used.
    """
    try:
        builder = writer._Writer__chunk_builder  # type: ignore[attr-defined]
        statistics = writer._Writer__statistics  # type: ignore[attr-defined]
        finalize = writer._Writer__finalize_chunk  # type: ignore[attr-defined]
        builder.record_writer._buffer.tell
        builder.message_indices, builder.num_messages, builder.message_start_time, builder.message_end_time
        statistics.channel_message_counts, statistics.message_count
        statistics.message_start_time, statistics.message_end_time
    except AttributeError:
        return None
    if builder is None:
        return None
    return builder, statistics, finalize


class _Encoder:
    """Encodes rows into the MCAP file."""

    def __init__(
        self,
        path: Path,
        components: Sequence[tuple[str, Sequence[str]]],
        descriptions: dict[str, dict[str, str]] | None,
        foxglove: "FoxgloveChannels | None",
        flush_interval: float,
        chunk_size: int,
        fast: bool = True,
    ) -> None:
        self.path = Path(path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._file = open(self.path, "wb")
        self._writer = Writer(self._file, compression=CompressionType.ZSTD, chunk_size=chunk_size)
        self._writer.start(profile="", library="platoon-cosim")
        self.components = [(name, list(outputs)) for name, outputs in components]
        self._channels = []
        for name, outputs in self.components:
            schema_id = self._writer.register_schema(
                name=f"platoon.{name}",
                encoding=SCHEMA_ENCODING,
                data=_schema(name, outputs, (descriptions or {}).get(name, {})),
            )
            self._channels.append(
                self._writer.register_channel(topic=channel_name(name), message_encoding=MESSAGE_ENCODING,
                                              schema_id=schema_id, metadata={KIND_KEY: "component"})
            )
        self.foxglove = foxglove
        if foxglove is not None:
            foxglove.register(self._writer)
        self._templates = [_template(["t", *outputs]).encode() for _, outputs in self.components]
        self._spans, start = [], 1
        for _, outputs in self.components:  # where each component's values sit in a row's flat list
            self._spans.append((start, start + len(outputs)))
            start += len(outputs)
        self._chunk_size = chunk_size
        self._fast = _fast_path(self._writer) if fast else None
        self._chunk_indexes = getattr(self._writer, "_Writer__chunk_indices", None)
        self._packed = 0
        self.flush_interval = flush_interval
        self.recorded = 0
        self.last_time: float | None = None
        self._last_chunk = clock.monotonic()

    def _write(self, channel: int, stamp: int, data: bytes) -> None:
        self._add(stamp, self.recorded, ((channel, data),))

    def _add(self, stamp: int, sequence: int, messages: Sequence[tuple[int, bytes]]) -> None:
        """Add messages that share one log time (= publish time) and sequence number."""
        fast = self._fast
        if fast is None:
            write = self._writer.add_message
            for channel, data in messages:
                write(channel_id=channel, log_time=stamp, publish_time=stamp, sequence=sequence, data=data)
            return
        builder, statistics, finalize = fast
        buffer = builder.record_writer._buffer  # a new one after every chunk
        indexes = builder.message_indices
        counts = statistics.channel_message_counts
        pack = _MESSAGE_HEADER.pack
        for channel, data in messages:
            index = indexes.get(channel)
            if index is None:
                index = indexes[channel] = _MessageIndex(channel_id=channel, records=[])
            index.records.append((stamp, buffer.tell()))
            buffer.write(pack(_MESSAGE_OPCODE, 22 + len(data), channel, sequence, stamp, stamp))
            buffer.write(data)
            counts[channel] += 1
        if builder.num_messages == 0:
            builder.message_start_time = builder.message_end_time = stamp
        else:
            builder.message_start_time = min(builder.message_start_time, stamp)
            builder.message_end_time = max(builder.message_end_time, stamp)
        builder.num_messages += len(messages)
        if statistics.message_count == 0:
            statistics.message_start_time = statistics.message_end_time = stamp
        else:
            statistics.message_start_time = min(statistics.message_start_time, stamp)
            statistics.message_end_time = max(statistics.message_end_time, stamp)
        statistics.message_count += len(messages)
        if buffer.tell() > self._chunk_size:
            finalize()
            self._pack_indexes()

    def _pack_indexes(self) -> None:
        indexes = self._chunk_indexes
        if isinstance(indexes, list):
            for position in range(self._packed, len(indexes)):
                indexes[position] = _PackedRecord(indexes[position])
            self._packed = len(indexes)

    def rows(self, rows: Sequence[tuple[float, Sequence[Sequence[float]]]]) -> None:
        """Write rows (all finite); close the chunk and flush the file if ``flush_interval`` passed."""
        channels, templates, foxglove = self._channels, self._templates, self.foxglove
        spans = self._spans
        for time, outputs in rows:
            stamp = int(round(time * 1e9))
            flat = [time]
            for values in outputs:
                flat.extend(values)
            texts = number_texts(flat)  # one conversion per row: the costly part of JSON
            first = texts[0]
            messages = [(channel, template % (first, *texts[start:end]))
                        for channel, template, (start, end) in zip(channels, templates, spans)]
            if foxglove is not None:
                messages.extend(foxglove.row(time, stamp, outputs))
            self._add(stamp, self.recorded, messages)
            self.recorded += 1
            self.last_time = time
        self.tick()

    def tick(self) -> None:
        now = clock.monotonic()
        if now - self._last_chunk >= self.flush_interval:
            flush = getattr(self._writer, "flush", None)
            if flush is not None:  # mcap >= 1.3: finishes the chunk and flushes the stream
                flush()
            else:
                self._writer._Writer__finalize_chunk()  # type: ignore[attr-defined]
                self._file.flush()
            self._last_chunk = now
        self._pack_indexes()

    def log(self, time: float, level: str, message: str) -> None:
        if self.foxglove is not None:
            self.foxglove.log(self._write, time, level, message)

    def metadata(self, name: str, values: dict[str, str]) -> None:
        self._writer.add_metadata(name, values)
        self._file.flush()

    def close(self) -> None:
        self._writer.finish()
        self._file.close()


class TraceWriter:
    """Writes a run's trace; ``record`` is cheap, ``flush`` hands buffered rows to the encoder."""

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
    ) -> None:
        self.path = Path(path)
        self.components = [(name, list(outputs)) for name, outputs in components]
        self._encoder = _Encoder(self.path, self.components, descriptions, foxglove, flush_interval, chunk_size)
        self.foxglove = foxglove
        self._keys = [["t", *outputs] for _, outputs in self.components]
        self.every = every
        self.block = block
        self.flush_interval = flush_interval
        self._count = 0
        self._rows: list[tuple[float, list[list[float]]]] = []
        self.recorded = 0  # rows handed to the encoder so far
        self.last_time: float | None = None  # simulation time of the last row handed over
        self._last_flush = clock.monotonic()
        self._closed = False

    def record(self, time: float, outputs: Sequence[Sequence[float]]) -> None:
        """Keep the outputs at ``time`` (every ``every``-th call) for the next flush."""
        if self._count % self.every == 0:
            rows = self._rows
            rows.append((time, [list(values) for values in outputs]))
            if len(rows) >= self.block or clock.monotonic() - self._last_flush >= self.flush_interval:
                self.flush()
        self._count += 1

    @property
    def rows_recorded(self) -> int:
        """Rows recorded so far, handed over or still buffered."""
        return self.recorded + len(self._rows)

    def _deliver(self, rows: list[tuple[float, list[list[float]]]]) -> None:
        if rows:
            self._encoder.rows(rows)
            self.recorded += len(rows)
            self.last_time = rows[-1][0]
        else:
            self._encoder.tick()

    def flush(self) -> None:
        """Hand the buffered rows to the encoder.

        A row holding a non-finite output is not written: the rows before it are, the rest of the
        buffer is dropped, and ``ComponentError`` names the component, the output and the time.
        """
        rows, self._rows = self._rows, []
        self._last_flush = clock.monotonic()
        for index, (time, outputs) in enumerate(rows):
            for values in outputs:
                if not math.isfinite(sum(values)):
                    self._deliver(rows[:index])
                    self._non_finite(time, outputs)
        self._deliver(rows)

    def _non_finite(self, time: float, outputs: Sequence[Sequence[float]]) -> None:
        for (name, _), values, keys in zip(self.components, outputs, self._keys):
            for key, value in zip(keys[1:], values):
                if not math.isfinite(value):
                    raise ComponentError(name, time, f"output {key} = {value} is not finite (the trace ends before it)")
        raise ComponentError(self.components[0][0], time, "outputs overflow")

    def log(self, time: float, level: str, message: str) -> None:
        """A line on ``/platoon/log`` (foxglove.Log) at simulation ``time``: Info, Warning or Error."""
        if self.foxglove is not None and not self._closed:
            self._encoder.log(time, level, message)

    def metadata(self, name: str, values: dict[str, Any]) -> None:
        self._encoder.metadata(name, {k: v if isinstance(v, str) else json.dumps(v) for k, v in values.items()})

    def close(self) -> None:
        if self._closed:
            return
        self._closed = True
        try:
            self.flush()
        finally:
            self._encoder.close()


class NullTraceWriter:
    """Records nothing: ``run_scenario(..., out=None)`` runs with this (benchmarks, dry runs)."""

    foxglove = None
    recorded = 0
    rows_recorded = 0
    last_time = None

    def record(self, time: float, outputs: Sequence[Sequence[float]]) -> None:
        pass

    def flush(self) -> None:
        pass

    def log(self, time: float, level: str, message: str) -> None:
        pass

    def metadata(self, name: str, values: dict[str, Any]) -> None:
        pass

    def close(self) -> None:
        pass


# --- reading ---------------------------------------------------------------------------------------

@dataclass(frozen=True)
class TopicInfo:
    topic: str
    schema: str
    message_encoding: str
    kind: str  # "component", "errors", "foxglove" or "other"
    messages: int


@dataclass(frozen=True)
class LogLine:
    t: float
    level: str
    message: str


@dataclass
class Trace:
    """A trace read back: per component, a dict of numpy arrays keyed by ``t`` and output names.

    ``channels`` holds only the components (``/platoon/<component>``); ``errors`` the flattened
    ``/platoon/errors`` columns (``t``, ``vehicle1.path_error`` ...); ``log`` the ``/platoon/log``
    lines; ``topics`` every channel of the file with its schema and message count.
    """

    path: Path
    channels: dict[str, dict[str, np.ndarray]]
    metadata: dict[str, dict[str, str]] = field(default_factory=dict)
    errors: dict[str, np.ndarray] = field(default_factory=dict)
    log: list[LogLine] = field(default_factory=list)
    topics: dict[str, TopicInfo] = field(default_factory=dict)

    @property
    def config(self) -> dict[str, Any] | None:
        record = self.metadata.get("platoon.config")
        return json.loads(record["resolved"]) if record and "resolved" in record else None

    @property
    def run(self) -> dict[str, str]:
        return self.metadata.get("platoon.run", {})

    def component(self, name: str) -> dict[str, np.ndarray]:
        return self.channels[name]

    def vehicles(self) -> list[str]:
        names = [n for n in self.channels if n.startswith("vehicle") and n[len("vehicle"):].isdigit()]
        return sorted(names, key=lambda n: int(n[len("vehicle"):]))


def _kind(channel: Channel, schema: Schema | None) -> str:
    if KIND_KEY in channel.metadata:
        return channel.metadata[KIND_KEY]
    # traces written before channel kinds existed: every JSON /platoon/ channel was a component
    if channel.topic.startswith(CHANNEL_PREFIX) and channel.message_encoding == MESSAGE_ENCODING:
        return "errors" if channel.topic == ERRORS_TOPIC else "component"
    return "foxglove" if schema is not None and schema.name.startswith("foxglove.") else "other"


def _flatten(record: dict[str, Any], prefix: str = "") -> dict[str, Any]:
    flat: dict[str, Any] = {}
    for key, value in record.items():
        if isinstance(value, dict):
            flat.update(_flatten(value, f"{prefix}{key}."))
        else:
            flat[prefix + key] = value
    return flat


def _columns(keys: list[str], rows: list[list[float]]) -> dict[str, np.ndarray]:
    if not rows:
        return {key: np.zeros(0) for key in keys}
    array = np.asarray(rows, dtype=float)
    return {key: array[:, i].copy() for i, key in enumerate(keys)}


def load(path: str | Path) -> Trace:
    """Read a finished trace (CRCs checked) into numpy arrays, with its metadata, errors and log."""
    path = Path(path)
    with open(path, "rb") as stream:
        head = stream.read(len(MAGIC))
        stream.seek(max(0, path.stat().st_size - len(MAGIC)))
        tail = stream.read(len(MAGIC))
        stream.seek(0)
        if head != MAGIC:
            raise TraceError("not an MCAP file (no MCAP magic at its start)")
        if tail != MAGIC or path.stat().st_size < 2 * len(MAGIC) + FOOTER_LENGTH:
            raise TraceError(f"unfinished MCAP file (no footer: the writing process was killed?); "
                             f"recover its complete chunks with `platoon trace recover {path}`")
        reader = make_reader(stream, validate_crcs=True)
        try:
            summary = reader.get_summary()
        except Exception as error:  # a damaged footer or summary
            raise TraceError(f"damaged MCAP file ({error}); try `platoon trace recover {path}`") from None
        if summary is None:
            raise TraceError(f"no summary section (unfinished file?); try `platoon trace recover {path}`")
        kinds = {cid: _kind(ch, summary.schemas.get(ch.schema_id)) for cid, ch in summary.channels.items()}
        counts = summary.statistics.channel_message_counts if summary.statistics else {}
        topics = {
            ch.topic: TopicInfo(ch.topic, summary.schemas[ch.schema_id].name if ch.schema_id in summary.schemas else "",
                                ch.message_encoding, kinds[cid], counts.get(cid, 0))
            for cid, ch in summary.channels.items()
        }
        wanted = [ch.topic for cid, ch in summary.channels.items() if kinds[cid] in ("component", "errors") or ch.topic == LOG_TOPIC]
        rows: dict[str, list[list[float]]] = {}
        keys: dict[str, list[str]] = {}
        error_rows: list[list[float]] = []
        error_keys: list[str] = []
        log: list[LogLine] = []
        for _, channel, message in reader.iter_messages(topics=wanted, log_time_order=True):
            kind = kinds[channel.id]
            if kind == "component":
                name = channel.topic[len(CHANNEL_PREFIX):] if channel.topic.startswith(CHANNEL_PREFIX) else channel.topic
                record = json.loads(message.data)
                if name not in keys:
                    keys[name] = list(record)
                    rows[name] = []
                rows[name].append([record[k] for k in keys[name]])
            elif kind == "errors":
                record = _flatten(json.loads(message.data))
                if not error_keys:
                    error_keys = list(record)
                error_rows.append([record[k] for k in error_keys])
            elif channel.topic == LOG_TOPIC:
                log.append(decode_log(message.data))
        metadata = {item.name: dict(item.metadata) for item in reader.iter_metadata()}
    for cid, ch in summary.channels.items():  # a component with no message yet still appears, empty
        if kinds[cid] == "component":
            name = ch.topic[len(CHANNEL_PREFIX):]
            if name not in rows:
                schema = summary.schemas.get(ch.schema_id)
                keys[name] = list(json.loads(schema.data)["properties"]) if schema is not None else ["t"]
                rows[name] = []
    channels = {name: _columns(keys[name], rows[name]) for name in rows}
    errors = _columns(error_keys, error_rows) if error_keys else {}
    return Trace(path, channels, metadata, errors, log, topics)


_LEVELS = {0: "Unknown", 1: "Debug", 2: "Info", 3: "Warning", 4: "Error", 5: "Fatal"}


def _varint(data: bytes, at: int) -> tuple[int, int]:
    value, shift = 0, 0
    while True:
        byte = data[at]
        value |= (byte & 0x7F) << shift
        at += 1
        if not byte & 0x80:
            return value, at
        shift += 7


def decode_log(data: bytes) -> LogLine:
    """A ``foxglove.Log`` protobuf message: timestamp (1), level (2) and message (3); the rest skipped."""
    fields: dict[int, Any] = {}
    at = 0
    while at < len(data):
        tag, at = _varint(data, at)
        number, wire = tag >> 3, tag & 7
        if wire == 0:
            fields[number], at = _varint(data, at)
        elif wire == 2:
            length, at = _varint(data, at)
            fields[number] = data[at:at + length]
            at += length
        elif wire == 5:
            at += 4
        elif wire == 1:
            at += 8
        else:
            raise ValueError(f"unexpected protobuf wire type {wire}")
    sec = nsec = 0
    stamp = fields.get(1, b"")
    at = 0
    while at < len(stamp):
        tag, at = _varint(stamp, at)
        value, at = _varint(stamp, at)
        if tag >> 3 == 1:
            sec = value
        elif tag >> 3 == 2:
            nsec = value
    return LogLine(sec + nsec * 1e-9, _LEVELS.get(fields.get(2, 0), "Unknown"), fields.get(3, b"").decode("utf-8", "replace"))


# --- export ----------------------------------------------------------------------------------------

def export_csv(trace: Trace, directory: str | Path) -> list[Path]:
    """One ``<component>.csv`` per component (header ``t`` then the outputs), and ``errors.csv``.

    Values are written with ``repr``, which round-trips every float exactly.
    """
    directory = Path(directory)
    directory.mkdir(parents=True, exist_ok=True)
    tables = dict(trace.channels)
    if trace.errors:
        tables["errors"] = trace.errors
    written = []
    for name, columns in tables.items():
        path = directory / f"{name}.csv"
        keys = list(columns)
        with open(path, "w", newline="") as stream:
            out = csv.writer(stream)
            out.writerow(keys)
            for row in zip(*(columns[k].tolist() for k in keys)):
                out.writerow([repr(v) for v in row])
        written.append(path)
    return written


# --- recovery --------------------------------------------------------------------------------------

@dataclass(frozen=True)
class Recovery:
    source: Path
    destination: Path
    chunks: int  # complete chunks read
    messages: int  # messages written
    dropped: int  # messages of complete chunks dropped past the last complete row
    steps: int  # rows (communication points) recovered
    last_time: float | None
    finished: bool  # the source had its footer (nothing was missing)


def recover(source: str | Path, destination: str | Path) -> Recovery:
    """Rewrite what an unfinished trace holds into a valid, indexed file.

    Reads records in file order with a non-seeking reader, keeps every chunk whose CRC checks and
    stops at the first record that is cut short or damaged. The result is trimmed to the last
    communication point that every component channel reached (a chunk may end inside a row), so all
    channels end at the same time. Metadata records are kept; if the run's ``platoon.run`` record
    is missing (the process was killed), one with status ``recovered`` is added.
    """
    source, destination = Path(source), Path(destination)
    schemas: dict[int, Schema] = {}
    channels: dict[int, Channel] = {}
    messages: list[Message] = []
    metadata: list[Metadata] = []
    chunks = 0
    finished = False
    with open(source, "rb") as stream:
        reader = StreamReader(stream, emit_chunks=True, validate_crcs=False, record_size_limit=1 << 30)
        try:
            for record in reader.records:
                if isinstance(record, Chunk):
                    try:
                        inner = breakup_chunk(record, validate_crc=True)
                    except Exception:
                        break
                    chunks += 1
                    records = inner
                else:
                    records = [record]
                for item in records:
                    if isinstance(item, Schema):
                        schemas[item.id] = item
                    elif isinstance(item, Channel):
                        channels[item.id] = item
                    elif isinstance(item, Message):
                        messages.append(item)
                    elif isinstance(item, Metadata):
                        metadata.append(item)
                if isinstance(record, (DataEnd, Footer)):
                    finished = True
                    break
        except McapError as error:
            if "magic" in str(error).lower() and chunks == 0 and not channels:
                raise TraceError(f"{source}: not an MCAP file ({error})") from None
        except Exception:  # cut short: EOF inside a record, a garbage length, ...
            pass
    components = {cid for cid, ch in channels.items() if _kind(ch, schemas.get(ch.schema_id)) == "component"}
    last: dict[int, int] = {}
    for message in messages:
        if message.channel_id in components:
            last[message.channel_id] = max(last.get(message.channel_id, -1), message.log_time)
    if components:
        complete = min(last.get(cid, -1) for cid in components)  # -1: some component has no message
        kept = [m for m in messages if m.log_time <= complete]
    else:
        complete, kept = None, messages
    dropped = len(messages) - len(kept)
    destination.parent.mkdir(parents=True, exist_ok=True)
    with open(destination, "wb") as stream:
        writer = Writer(stream, compression=CompressionType.ZSTD, chunk_size=CHUNK_SIZE)
        writer.start(profile="", library="platoon-cosim (recovered)")
        schema_ids = {sid: writer.register_schema(s.name, s.encoding, s.data) for sid, s in sorted(schemas.items())}
        channel_ids = {
            cid: writer.register_channel(c.topic, c.message_encoding, schema_ids.get(c.schema_id, 0), dict(c.metadata))
            for cid, c in sorted(channels.items())
        }
        kept.sort(key=lambda m: m.log_time)  # stable: file order within one time
        for m in kept:
            writer.add_message(channel_ids[m.channel_id], m.log_time, m.data, m.publish_time, m.sequence)
        names = {item.name for item in metadata}
        for item in metadata:
            writer.add_metadata(item.name, dict(item.metadata))
        first = min(components) if components else None
        steps = sum(1 for m in kept if m.channel_id == first)
        last_time = complete * 1e-9 if complete is not None and complete >= 0 else None
        if "platoon.run" not in names:
            start = next((dict(item.metadata) for item in metadata if item.name == "platoon.start"), {})
            writer.add_metadata("platoon.run", {
                "status": "recovered",
                "error": f"the run ended without finalizing its trace (killed?); recovered from {source.name}",
                "engine": start.get("engine", ""),
                "master": start.get("master", ""),
                "steps_recorded": str(steps),
                "last_time": "" if last_time is None else repr(last_time),
            })
        writer.finish()
    return Recovery(source, destination, chunks, len(kept), dropped, steps, last_time, finished)
