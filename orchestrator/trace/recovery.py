"""Recovering an unfinished trace (a killed run): keep every complete chunk, write a valid file."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from mcap.exceptions import McapError
from mcap.records import Channel, Chunk, DataEnd, Footer, Message, Metadata, Schema
from mcap.stream_reader import StreamReader, breakup_chunk
from mcap.writer import CompressionType, Writer

from .format import (
    CHUNK_SIZE,
    TraceError,
    channel_kind,
)


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
    components = {cid for cid, ch in channels.items() if channel_kind(ch, schemas.get(ch.schema_id)) == "component"}
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
