"""Recovering a trace that is unfinished (a killed run) or damaged (a flipped bit, garbage in the middle).

Every record is read in file order straight from the file, never the whole file at once: one pass
finds the intact records (a chunk is intact when it decompresses and its CRC checks), one pass copies
their messages into a new file. A damaged stretch is skipped: the reader looks for the next record
that checks (a chunk by its CRC, a metadata record by its exact structure) and goes on from there,
so one bad chunk loses only its own time range, which the result names. Memory holds one chunk at a
time, whatever the size of the file (docs/trace-format.md, "Recovering").
"""

from __future__ import annotations

import io
import json
import struct
from dataclasses import dataclass, field
from pathlib import Path
from typing import BinaryIO, Iterator

from mcap.data_stream import ReadDataStream
from mcap.records import Channel, Chunk, Message, Metadata, Schema
from mcap.stream_reader import breakup_chunk
from mcap.writer import CompressionType, Writer

from . import channel_copy
from .format import CHUNK_SIZE, MAGIC, TraceError, channel_kind, chunk_group

_HEADER = struct.Struct("<BQ")  # a record's opcode and content length
_CHUNK, _METADATA, _SCHEMA, _CHANNEL, _MESSAGE = 0x06, 0x0C, 0x03, 0x04, 0x05
_DATA_END, _FOOTER = 0x0F, 0x02
_KNOWN = set(range(0x01, 0x10))  # opcodes MCAP defines
# how to find the start of the next intact record after a damaged stretch: a marker inside it, and
# how far the record starts before the marker (our chunks are zstd; our metadata names are platoon.*)
_CHUNK_MARKER, _CHUNK_BACK = b"\x04\x00\x00\x00zstd", 1 + 8 + 8 + 8 + 8 + 4  # opcode .. CRC, then "zstd"
_METADATA_MARKER, _METADATA_BACK = b"platoon.", 1 + 8 + 4
_SEARCH_BLOCK = 1 << 20
_RECORD_LIMIT = 1 << 31  # a record claiming more than this is damage, not data


@dataclass(frozen=True)
class Recovery:
    source: Path
    destination: Path
    chunks: int  # intact chunks read
    messages: int  # messages written
    dropped: int  # messages of intact chunks dropped past the last complete row
    steps: int  # rows (communication points) recovered
    last_time: float | None
    finished: bool  # the source had its footer (its end was reached)
    # damaged stretches skipped, each as (after, before) in s of simulated time: the last intact
    # message time before it and the first after it (None: nothing intact before / after it)
    lost: list[tuple[float | None, float | None]] = field(default_factory=list)
    damaged: int = 0  # damaged stretches skipped
    cut: bool = False  # the file ends inside a record (the usual end of a killed run's file)
    refused_copies: int = 0  # platoon.channels copies refused: they contradict the file's own channels


@dataclass
class _Scan:
    schemas: dict[int, Schema] = field(default_factory=dict)
    channels: dict[int, Channel] = field(default_factory=dict)
    metadata: list[Metadata] = field(default_factory=list)
    chunks: list[int] = field(default_factory=list)  # offsets of intact chunks
    last: dict[int, int] = field(default_factory=dict)  # per channel: latest log time
    lost: list[tuple[int | None, int | None]] = field(default_factory=list)  # ns
    awaited: set[int] = field(default_factory=set)  # chunk groups not seen since the last damage (_ANY: any)
    damaged: int = 0
    finished: bool = False
    cut: bool = False  # the file ends inside a record (a killed run's last chunk)
    copies: list[channel_copy.ChannelCopy] = field(default_factory=list)  # platoon.channels records that decoded
    copied: dict[int, Channel] = field(default_factory=dict)  # their channels by id, first seen: groups while scanning
    refused_copies: int = 0


def _read_at(stream: BinaryIO, position: int, size: int) -> bytes:
    stream.seek(position)
    return stream.read(size)


def _parse(stream: BinaryIO, position: int, size: int) -> tuple[int, int, object] | None:
    """The record at ``position``: (opcode, end offset, parsed content or None); None if it does not check."""
    head = _read_at(stream, position, _HEADER.size)
    if len(head) < _HEADER.size:
        return None
    opcode, length = _HEADER.unpack(head)
    end = position + _HEADER.size + length
    if opcode not in _KNOWN or length > _RECORD_LIMIT or end > size:
        return None
    if opcode in (_DATA_END, _FOOTER):
        return opcode, end, None
    if opcode not in (_CHUNK, _METADATA, _SCHEMA, _CHANNEL, _MESSAGE):
        return opcode, end, None  # indexes, statistics, attachments: rebuilt or not ours; skipped
    body = stream.read(length)
    data = ReadDataStream(io.BytesIO(body))
    try:
        if opcode == _CHUNK:
            chunk = Chunk.read(data)
            if data.count != length:
                return None
            return opcode, end, breakup_chunk(chunk, validate_crc=True)
        record = {_METADATA: Metadata, _SCHEMA: Schema, _CHANNEL: Channel}.get(opcode)
        parsed = Message.read(data, length) if record is None else record.read(data)
        if data.count != length:
            return None
        return opcode, end, parsed
    except Exception:  # bad lengths, bad UTF-8, a CRC mismatch, zstd errors: damage
        return None


def _resync(stream: BinaryIO, start: int, size: int) -> tuple[int, tuple[int, int, object]] | None:
    """The first intact chunk or metadata record at or after ``start``, with where it starts."""
    overlap = max(len(_CHUNK_MARKER), len(_METADATA_MARKER))
    block_start = start
    while block_start < size:
        block = _read_at(stream, block_start, _SEARCH_BLOCK + overlap)
        candidates = []
        for marker, back in ((_CHUNK_MARKER, _CHUNK_BACK), (_METADATA_MARKER, _METADATA_BACK)):
            found = block.find(marker)
            while found >= 0:
                candidates.append(block_start + found - back)
                found = block.find(marker, found + 1)
        for candidate in sorted(set(candidates)):
            if candidate >= start:
                parsed = _parse(stream, candidate, size)
                if parsed is not None and parsed[0] in (_CHUNK, _METADATA):
                    return candidate, parsed
        block_start += _SEARCH_BLOCK
    return None


def _records(stream: BinaryIO, size: int, scan: _Scan) -> Iterator[tuple[int, int, object]]:
    """Intact records in file order (position, opcode, content), skipping damage and noting it in ``scan``.

    The data section and then the summary (whose schema and channel records are a second copy of the
    chunks' ones). A record whose content is not checked (an index) is trusted only for its length;
    if what follows does not check, the search for the next intact record starts again right after
    the last record that did check, so a damaged length never jumps over an intact chunk.
    """
    position = resume = len(MAGIC)
    while position < size:
        parsed = _parse(stream, position, size)
        if parsed is not None and (parsed[0] == _MESSAGE  # our messages are all in chunks: a loose one is damage
                                   or (parsed[0] == _FOOTER and parsed[1] + len(MAGIC) != size)):  # not at the end
            parsed = None
        if parsed is None:
            found = _resync(stream, resume, size)
            if found is None:  # nothing intact follows: the file is cut short here
                scan.cut = not scan.finished
                return
            scan.damaged += 1
            latest = _group_latest(scan)
            scan.lost.append((min(latest.values(), default=None), None))
            scan.awaited = set(latest) or {_ANY}
            position, parsed = found
        opcode, end, content = parsed
        if opcode == _FOOTER:
            return
        if opcode == _DATA_END:
            scan.finished = True  # the summary follows: its schemas and channels are read too
        elif content is not None:
            yield position, opcode, content
            resume = end
        position = end


_ANY = -2  # awaited: the damage is before any message; the first intact one after it ends the stretch


def _group_of(scan: _Scan, channel: int) -> int:
    known = scan.channels.get(channel) or scan.copied.get(channel)
    return -1 if known is None else chunk_group(known.topic)


def _group_latest(scan: _Scan) -> dict[int, int]:
    """Per chunk group (trace/format.py: chunk_group), the latest log time read so far.

    Each group has chunks of its own, closed together at one row and written back to back; a damaged
    chunk is one group's, and which one cannot be told. So a damaged stretch starts where the group
    that reached least far stopped, and ends where the group that resumes last resumes (for a file
    written with one chunk for every channel: the last message before it, the first after it)."""
    latest: dict[int, int] = {}
    for channel, stamp in scan.last.items():
        group = _group_of(scan, channel)
        latest[group] = max(latest.get(group, stamp), stamp)
    return latest


def _resumed(scan: _Scan, firsts: dict[int, int]) -> None:
    """An intact chunk after a damaged stretch (``firsts``: its groups' first log times) may end the stretch."""
    if not scan.awaited or not firsts:
        return
    for group, first in firsts.items():
        if group in scan.awaited or _ANY in scan.awaited:
            start, end = scan.lost[-1]
            scan.lost[-1] = (start, first if end is None else max(end, first))
            scan.awaited.discard(group)
    scan.awaited.discard(_ANY)


def _keep_definition(scan: _Scan, item: Schema | Channel) -> None:
    """A schema or channel of an intact chunk or of the summary: the file's own word on it."""
    table = scan.schemas if isinstance(item, Schema) else scan.channels
    table.setdefault(item.id, item)


def _adopt_copies(scan: _Scan) -> None:
    """Fill in, from the platoon.channels copies, what no intact chunk defined (its first chunk damaged): checked
    copies before unchecked ones, and each copy whole or not at all. A copy that contradicts a definition already
    held (a chunk's own, or a copy trusted more: the same id, another topic or schema) is not this file's copy as
    written (spliced from another run, or damaged where no CRC guards it) and gives nothing: it would relabel
    intact channels."""
    for copy in sorted(scan.copies, key=lambda copy: not copy.checked):
        held = [(scan.schemas, copy.schemas), (scan.channels, copy.channels)]
        if any(table.get(item.id, item) != item for table, items in held for item in items):
            scan.refused_copies += 1
            continue
        for table, items in held:
            for item in items:
                table.setdefault(item.id, item)


def _scan(stream: BinaryIO, size: int) -> _Scan:
    scan = _Scan()
    for position, opcode, content in _records(stream, size, scan):
        items = content if opcode == _CHUNK else [content]
        if opcode == _CHUNK:
            scan.chunks.append(position)
        firsts: dict[int, int] = {}  # per chunk group
        for item in items:
            if isinstance(item, (Schema, Channel)):
                _keep_definition(scan, item)
            elif isinstance(item, Metadata) and item.name == channel_copy.NAME:
                if (copy := channel_copy.decode(item)) is not None:
                    scan.copies.append(copy)
                    for channel in copy.channels:
                        scan.copied.setdefault(channel.id, channel)
            elif isinstance(item, Metadata):
                scan.metadata.append(item)
            elif isinstance(item, Message):
                group = _group_of(scan, item.channel_id)
                firsts[group] = min(firsts.get(group, item.log_time), item.log_time)
                scan.last[item.channel_id] = max(scan.last.get(item.channel_id, item.log_time), item.log_time)
        _resumed(scan, firsts)  # the damage ends where intact messages resume
    _adopt_copies(scan)
    return scan


def _check_source(stream: BinaryIO, source: Path, size: int) -> None:
    if size == 0:
        raise TraceError(f"trace {source}: is empty (0 bytes), nothing to recover")
    if _read_at(stream, 0, len(MAGIC)) != MAGIC:
        raise TraceError(f"trace {source}: not an MCAP file (no MCAP magic at its start), nothing to recover")


def recover(source: str | Path, destination: str | Path) -> Recovery:
    """Rewrite what an unfinished or damaged trace holds into a valid, indexed file at ``destination``.

    Keeps every intact chunk, skipping damaged stretches (``Recovery.lost`` names the simulated time
    they held). The result is trimmed to the last communication point that every component channel
    reached (a chunk may end inside a row), so all channels end at the same time. Metadata records
    are kept; if the run's ``platoon.run`` record is missing (the process was killed), one with
    status ``recovered`` is added, and ``platoon.recovery`` says what was lost. ``destination`` is
    written as given (the command line writes it aside and renames it: trace/output.py). Raises
    ``TraceError`` for an empty or non-MCAP source.
    """
    source, destination = Path(source), Path(destination)
    with open(source, "rb") as stream:
        size = source.stat().st_size
        _check_source(stream, source, size)
        scan = _scan(stream, size)
        if not scan.channels and not scan.metadata:
            raise TraceError(f"trace {source}: holds no intact MCAP record (no channel, no metadata), nothing to recover")
        schemas, channels = scan.schemas, scan.channels
        components = {cid for cid, ch in channels.items()
                      if channel_kind(ch, schemas.get(ch.schema_id)) == "component"}
        complete = min((scan.last.get(cid, -1) for cid in components), default=None)  # -1: a component never wrote
        with open(destination, "wb") as out:
            writer = Writer(out, compression=CompressionType.ZSTD, chunk_size=CHUNK_SIZE)
            writer.start(profile="", library="platoon-cosim (recovered)")
            schema_ids = {sid: writer.register_schema(s.name, s.encoding, s.data) for sid, s in sorted(schemas.items())}
            channel_ids = {cid: writer.register_channel(c.topic, c.message_encoding, schema_ids.get(c.schema_id, 0),
                                                        dict(c.metadata))
                           for cid, c in sorted(channels.items())}
            channel_copy.write_copy(  # the recovered file keeps a second copy too, with its own ids
                writer, [Schema(id=new, name=schemas[old].name, encoding=schemas[old].encoding, data=schemas[old].data)
                         for old, new in schema_ids.items()],
                [Channel(id=new, schema_id=schema_ids.get(channels[old].schema_id, 0), topic=channels[old].topic,
                         message_encoding=channels[old].message_encoding, metadata=dict(channels[old].metadata))
                 for old, new in channel_ids.items()])
            first = min(components) if components else None
            kept = dropped = steps = 0
            for position in scan.chunks:  # second pass: one chunk in memory at a time
                parsed = _parse(stream, position, size)
                assert parsed is not None  # it checked in the first pass
                for item in parsed[2]:  # type: ignore[union-attr]
                    if not isinstance(item, Message) or item.channel_id not in channel_ids:
                        continue
                    if complete is not None and item.log_time > complete:
                        dropped += 1
                        continue
                    writer.add_message(channel_ids[item.channel_id], item.log_time, item.data, item.publish_time,
                                       item.sequence)
                    kept += 1
                    steps += item.channel_id == first
            names = {item.name for item in scan.metadata}
            for item in scan.metadata:
                if item.name != "platoon.recovery":
                    writer.add_metadata(item.name, dict(item.metadata))
            last_time = complete * 1e-9 if complete is not None and complete >= 0 else None
            if "platoon.run" not in names:
                start = next((dict(item.metadata) for item in scan.metadata if item.name == "platoon.start"), {})
                writer.add_metadata("platoon.run", {
                    "status": "recovered",
                    "error": f"the run ended without finalizing its trace (killed?); recovered from {source.name}",
                    "engine": start.get("engine", ""),
                    "master": start.get("master", ""),
                    "steps_recorded": str(steps),
                    "last_time": "" if last_time is None else repr(last_time),
                })
            lost = [(None if a is None else a * 1e-9, None if b is None else b * 1e-9) for a, b in scan.lost]
            writer.add_metadata("platoon.recovery", {
                "source": source.name,
                "finished": "true" if scan.finished else "false",
                "chunks": str(len(scan.chunks)),
                "damaged": str(scan.damaged),
                "cut_short": "true" if scan.cut else "false",
                "lost": json.dumps(lost),
                "refused_channel_copies": str(scan.refused_copies),
            })
            writer.finish()
    return Recovery(source, destination, len(scan.chunks), kept, dropped, steps, last_time, scan.finished,
                    lost, scan.damaged, scan.cut, scan.refused_copies)


def describe_lost(lost: list[tuple[float | None, float | None]]) -> str:
    """``t = 10.2 .. 11.4 s`` per lost stretch ("the start" / "the end" for open sides), comma-separated."""
    def side(value: float | None, open_text: str) -> str:
        return open_text if value is None else f"{value:.6g}"
    return ", ".join(f"t = {side(a, 'start')} .. {side(b, 'end')} s" for a, b in lost)
