"""Reading traces back: components as numpy arrays, the error channel, log lines, metadata; CSV export."""

from __future__ import annotations

import csv
import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Iterable

import numpy as np
from mcap.data_stream import ReadDataStream
from mcap.exceptions import McapError
from mcap.reader import make_reader
from mcap.records import Chunk, Message
from mcap.stream_reader import breakup_chunk

from .format import (
    CHANNEL_PREFIX,
    LOG_TOPIC,
    MAGIC,
    FOOTER_LENGTH,
    TraceError,
    channel_kind,
    vehicle_names,
)


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
    # a live vehicle's raw link messages, by stream: "vehicle3/pose", "vehicle3/command", "vehicle3/link"
    live: dict[str, dict[str, np.ndarray]] = field(default_factory=dict)

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
        return vehicle_names(self.channels)


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
        kinds = {cid: channel_kind(ch, summary.schemas.get(ch.schema_id)) for cid, ch in summary.channels.items()}
        counts = summary.statistics.channel_message_counts if summary.statistics else {}
        topics = {
            ch.topic: TopicInfo(ch.topic, summary.schemas[ch.schema_id].name if ch.schema_id in summary.schemas else "",
                                ch.message_encoding, kinds[cid], counts.get(cid, 0))
            for cid, ch in summary.channels.items()
        }
        wanted = [ch.topic for cid, ch in summary.channels.items() if kinds[cid] in ("component", "errors", "live") or ch.topic == LOG_TOPIC]
        rows: dict[str, list[list[float]]] = {}
        keys: dict[str, list[str]] = {}
        error_rows: list[list[float]] = []
        error_keys: list[str] = []
        log: list[LogLine] = []
        try:
            _read_messages(_in_file_order(reader, stream, summary, wanted), kinds, rows, keys, error_rows, error_keys, log)
        except TraceError:
            raise
        except Exception as error:  # a chunk fails its CRC, cannot be decompressed, or a record is damaged
            raise TraceError(f"damaged MCAP file: a chunk does not check ({error}); recover every intact chunk "
                             f"with `platoon trace recover {path}`") from None
        metadata = {item.name: dict(item.metadata) for item in reader.iter_metadata()}
    for cid, ch in summary.channels.items():  # a component with no message yet still appears, empty
        if kinds[cid] == "component":
            name = ch.topic[len(CHANNEL_PREFIX):]
            if name not in rows:
                schema = summary.schemas.get(ch.schema_id)
                keys[name] = list(json.loads(schema.data)["properties"]) if schema is not None else ["t"]
                rows[name] = []
    channels = {name: _columns(keys[name], rows[name]) for name in rows if not name.startswith(LIVE_KEY)}
    live = {name[len(LIVE_KEY):]: _columns(keys[name], rows[name]) for name in rows if name.startswith(LIVE_KEY)}
    errors = _columns(error_keys, error_rows) if error_keys else {}
    return Trace(path, channels, metadata, errors, log, topics, live)


def _in_file_order(reader: Any, stream: Any, summary: Any, wanted: list[str]) -> Iterable[tuple[Any, Message]]:
    """(channel, message) of the ``wanted`` topics, chunk by chunk in file order, each chunk's CRC checked.

    Not mcap's ``iter_messages(log_time_order=True)``: its priority queue over every message was 40 % of
    reading a trace, and a channel's messages are in time order in the file already (the writer, the trace
    worker and recovery write them so); ``_read_messages`` puts any channel that is not back in order."""
    if not summary.chunk_indexes:  # messages outside chunks (another writer's file): mcap reads them linearly
        yield from ((channel, message) for _, channel, message in reader.iter_messages(topics=wanted))
        return
    topics = set(wanted)
    for index in sorted(summary.chunk_indexes, key=lambda chunk: chunk.chunk_start_offset):
        stream.seek(index.chunk_start_offset + 1 + 8)  # past the record's opcode and length
        for record in breakup_chunk(Chunk.read(ReadDataStream(stream)), validate_crc=True):
            if isinstance(record, Message):
                channel = summary.channels[record.channel_id]
                if channel.topic in topics:
                    yield channel, record


def _read_messages(messages: Iterable[tuple[Any, Message]], kinds: dict[int, str], rows: dict[str, list[list[float]]],
                   keys: dict[str, list[str]], error_rows: list[list[float]], error_keys: list[str],
                   log: list[LogLine]) -> None:
    """Decode the wanted channels' messages into the row and log lists, each channel's in log-time order
    (ties in file order: what mcap's log-time order gives)."""
    times: dict[int, list[int]] = {}  # per channel, its messages' log times, in the order read
    lists: dict[int, list[Any]] = {}  # per channel, the list its messages went to
    for channel, message in messages:
        times.setdefault(channel.id, []).append(message.log_time)
        kind = kinds[channel.id]
        if kind in ("component", "live"):
            name = channel.topic[len(CHANNEL_PREFIX):] if channel.topic.startswith(CHANNEL_PREFIX) else channel.topic
            if kind == "live":
                name = LIVE_KEY + name
            record = json.loads(message.data)
            if name not in keys:
                keys[name] = list(record)
                rows[name] = []
            lists[channel.id] = rows[name]
            rows[name].append([record[k] for k in keys[name]])
        elif kind == "errors":
            record = _flatten(json.loads(message.data))
            if not error_keys:
                error_keys.extend(record)
            lists[channel.id] = error_rows
            error_rows.append([record[k] for k in error_keys])
        elif channel.topic == LOG_TOPIC:
            lists[channel.id] = log
            log.append(decode_log(message.data))
    for channel_id, read in times.items():
        if any(later < earlier for earlier, later in zip(read, read[1:])):
            order = np.argsort(np.asarray(read), kind="stable")
            lists[channel_id][:] = [lists[channel_id][i] for i in order]


LIVE_KEY = "\0live:"  # keeps live streams apart from components while reading (no topic holds a NUL)


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

def export_csv(trace: Trace, directory: str | Path, overwrite: bool = False, protect: Iterable[Path] = ()) -> list[Path]:
    """One ``<component>.csv`` per component (header ``t`` then the outputs), and ``errors.csv``.

    Values are written with ``repr``, which round-trips every float exactly. By the output rule
    (orchestrator/support/output.py): all targets are checked before the first is written (a CSV this
    export wrote is replaced, anything else only with ``overwrite``, an input never), each is written
    aside and renamed into place; ``OutputError`` (one line) if one may not or cannot be.
    """
    from orchestrator.support.output import Kind, check_folder, check_target, replacing, starts_with

    directory = Path(directory)
    check_folder(directory, protect, "--csv")
    tables = dict(trace.channels)
    if trace.errors:
        tables["errors"] = trace.errors
    targets = {name: directory / f"{name}.csv" for name in tables}
    for path in targets.values():
        check_target(path, overwrite, protect, "--csv", kind=Kind("a CSV this export wrote (header starting with t)", starts_with(b"t,", b"t\r\n", b"t\n")))
    for name, columns in tables.items():
        keys = list(columns)
        with replacing(targets[name], "--csv") as aside, open(aside, "w", newline="") as stream:
            out = csv.writer(stream)
            out.writerow(keys)
            for row in zip(*(columns[k].tolist() for k in keys)):
                out.writerow([repr(v) for v in row])
    return list(targets.values())
