"""Reading traces back: components as numpy arrays, the error channel, log lines, metadata; CSV export."""

from __future__ import annotations

import csv
import json
import struct
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Iterable

import numpy as np
from mcap.reader import make_reader

from .columns import NO_LIMIT, ChunkDecoder, JsonColumns, RawMessages, Slot, decode_chunks, message_counts
from .summary_section import check_ends, metadata_records

from .format import (
    CHANNEL_PREFIX,
    LOG_TOPIC,
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
    # (start, end) in s when only that window was read (``load(start=, end=)``; None: an open end)
    window: tuple[float | None, float | None] | None = None

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


def load(path: str | Path, *, components: Iterable[str] | Callable[[str], bool] | None = None, start: float | None = None,
         end: float | None = None, errors: bool = True,
         progress: Callable[[int, int], None] | None = None) -> Trace:
    """Read a finished trace (CRCs checked) into numpy arrays, with its metadata, errors and log.

    ``components`` (names such as ``vehicle3``, ``target``, or a test of a name; a live vehicle's streams
    come with it) and ``errors=False`` leave channels out; ``start`` / ``end`` (s, inclusive) keep the messages logged in
    that window, and only the chunks that hold them are read: a slice costs in proportion to the slice.
    ``progress(done, total)`` is called after each chunk. The arrays are bit for bit what Python's json
    reads from the messages (orchestrator/trace/columns.py says how they are read fast).
    """
    path = Path(path)
    window = _window(start, end)
    with open(path, "rb") as stream:
        check_ends(path, stream)
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
        slots = _slots(summary, kinds, _chosen(summary, kinds, components), errors)
        try:
            _decode_file(path, reader, summary, slots, window, progress)
        except (TraceError, ValueError, TypeError, KeyError, OverflowError, struct.error) as error:  # a bad CRC, chunk, record or message
            raise TraceError(f"damaged MCAP file: a chunk does not check ({error}); recover every intact chunk "
                             f"with `platoon trace recover {path}`") from None
        metadata = metadata_records(reader)
    return _assemble(path, summary, kinds, slots, metadata, topics, start, end)


def _window(start: float | None, end: float | None) -> tuple[int, int]:
    """The log-time window in ns (the writer's ``round(t * 1e9)``)."""
    lo = 0 if start is None else max(0, round(start * 1e9))
    hi = NO_LIMIT[1] if end is None else round(end * 1e9)
    if hi < lo:
        raise TraceError(f"the time window is empty: start {start} s is after end {end} s")
    return lo, hi


def _component_of(topic: str) -> str:
    """The component a channel belongs to: ``/platoon/vehicle3/pose`` -> ``vehicle3``."""
    name = topic[len(CHANNEL_PREFIX):] if topic.startswith(CHANNEL_PREFIX) else topic
    return name.split("/", 1)[0]


def _chosen(summary: Any, kinds: dict[int, str],
            components: Iterable[str] | Callable[[str], bool] | None) -> set[str] | None:
    if components is None:
        return None
    present = {_component_of(ch.topic) for cid, ch in summary.channels.items() if kinds[cid] == "component"}
    if callable(components):
        return {name for name in present if components(name)}
    chosen = set(components)
    missing = sorted(chosen - present)
    if missing:
        raise TraceError(f"no component {', '.join(missing)} in this trace (it has {', '.join(sorted(present))})")
    return chosen


def _slots(summary: Any, kinds: dict[int, str], chosen: set[str] | None, errors: bool) -> dict[int, Slot]:
    """The channels to read, each with where its messages go."""
    slots: dict[int, Slot] = {}
    capacities = summary.statistics.channel_message_counts if summary.statistics else {}
    for cid, ch in summary.channels.items():
        kind = kinds[cid]
        if kind in ("component", "live") and (chosen is None or _component_of(ch.topic) in chosen):
            name = ch.topic[len(CHANNEL_PREFIX):] if ch.topic.startswith(CHANNEL_PREFIX) else ch.topic
            slots[cid] = JsonColumns(LIVE_KEY + name if kind == "live" else name, False, capacities.get(cid, 1024))
        elif kind == "errors" and errors:
            slots[cid] = JsonColumns(ch.topic, True, capacities.get(cid, 1024))
        elif ch.topic == LOG_TOPIC:
            slots[cid] = RawMessages(ch.topic)
    return slots


def _decode_file(path: Path, reader: Any, summary: Any, slots: dict[int, Slot], window: tuple[int, int],
                 progress: Callable[[int, int], None] | None) -> None:
    decoder = ChunkDecoder(slots, window)
    if not summary.chunk_indexes:  # messages outside chunks (another writer's file): mcap reads them linearly
        topics = [summary.channels[cid].topic for cid in slots]
        for _, channel, message in reader.iter_messages(topics=topics, log_time_order=False):
            decoder.message(channel.id, message.log_time, message.data)
        return
    chunks = [chunk for chunk in sorted(summary.chunk_indexes, key=lambda chunk: chunk.chunk_start_offset)
              if chunk.message_end_time >= window[0] and chunk.message_start_time <= window[1]
              and (not chunk.message_index_offsets or any(c in slots for c in chunk.message_index_offsets))]
    if window != NO_LIMIT and all(chunk.message_index_offsets for chunk in chunks):
        wanted = [cid for cid, slot in slots.items() if isinstance(slot, JsonColumns)]
        for cid, count in message_counts(str(path), chunks, wanted).items():
            slots[cid].capacity = count
    decode_chunks(str(path), [chunk.chunk_start_offset for chunk in chunks], decoder, progress)


def _assemble(path: Path, summary: Any, kinds: dict[int, str], slots: dict[int, Slot],
              metadata: dict[str, dict[str, str]], topics: dict[str, TopicInfo],
              start: float | None, end: float | None) -> Trace:
    channels: dict[str, dict[str, np.ndarray]] = {}
    live: dict[str, dict[str, np.ndarray]] = {}
    errors: dict[str, np.ndarray] = {}
    log: list[LogLine] = []
    json_slots = sorted((slot for slot in slots.values() if isinstance(slot, JsonColumns) and slot.values is not None),
                        key=lambda slot: slot.order)
    for slot in json_slots:
        if slot.nested:
            errors = slot.columns()
        elif slot.name.startswith(LIVE_KEY):
            live[slot.name[len(LIVE_KEY):]] = slot.columns()
        else:
            channels[slot.name] = slot.columns()
    for cid, slot in slots.items():  # a component with no message (in the window) still appears, empty
        if isinstance(slot, JsonColumns) and slot.values is None and kinds[cid] == "component":
            schema = summary.schemas.get(summary.channels[cid].schema_id)
            keys = list(json.loads(schema.data)["properties"]) if schema is not None else ["t"]
            channels[slot.name] = {key: np.zeros(0) for key in keys}
        elif isinstance(slot, RawMessages):
            log = [decode_log(data) for _, data in slot.ordered()]
    window = None if start is None and end is None else (start, end)
    return Trace(path, channels, metadata, errors, log, topics, live, window)


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
