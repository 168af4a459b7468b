"""A second copy of a trace's schemas and channels, outside the chunks, for `platoon trace recover`.

MCAP writes a schema and a channel record once, in the chunk that first uses them (the first chunk, for
every channel registered at the start), and once more in the summary at the end. A killed run has no
summary; so one damaged byte in its first chunk would leave every later chunk without channels, and
recovery could keep none of their messages. The copy is a metadata record, ``platoon.channels``,
written before the first chunk (metadata records are not chunked): JSON lists of the schemas (data in
base64) and channels, ids as in the file, and the CRC-32 of both lists. It is written twice, one record
after the other: a metadata record has no CRC of its own, and one damaged byte in a single copy and
another in the first chunk left a killed run's intact chunks with no channels (the recovery fuzz
campaign, tests/test_recovery_fuzz.py); the CRC keeps a damaged copy from defining a wrong channel.
Recovery takes channels and schemas from wherever they survive: the chunks and the summary first, then a
copy whose CRC checks, then one written before the CRC; a copy that contradicts what an intact chunk (or a
copy trusted more) defines is another file's, and none of it is taken (docs/trace-format.md, "Recovering").
"""

from __future__ import annotations

import base64
import json
import zlib
from dataclasses import dataclass
from typing import Any, Iterable

from mcap.records import Channel, Metadata, Schema

NAME = "platoon.channels"


def write_copy(writer: Any, schemas: Iterable[Schema], channels: Iterable[Channel]) -> None:
    """Add the ``platoon.channels`` records (``COPIES`` of them) of ``schemas`` and ``channels``, the ones
    ``writer`` (anything with ``add_metadata``: trace/mcap_file.py's file, an ``mcap`` Writer) registered."""
    copy = encode(schemas, channels)
    for _ in range(COPIES):
        writer.add_metadata(NAME, copy)


COPIES = 2


def _crc(schemas: str, channels: str) -> str:
    return str(zlib.crc32(f"{schemas}\0{channels}".encode()))


def encode(schemas: Iterable[Schema], channels: Iterable[Channel]) -> dict[str, str]:
    listed = {
        "schemas": json.dumps([{"id": s.id, "name": s.name, "encoding": s.encoding,
                                "data": base64.b64encode(s.data).decode()} for s in schemas]),
        "channels": json.dumps([{"id": c.id, "schema_id": c.schema_id, "topic": c.topic,
                                 "message_encoding": c.message_encoding, "metadata": dict(c.metadata)}
                                for c in channels]),
    }
    return {**listed, "crc32": _crc(listed["schemas"], listed["channels"])}


@dataclass(frozen=True)
class ChannelCopy:
    """One ``platoon.channels`` record, decoded: its schemas and channels, and whether its CRC-32 checked (a copy
    written before the CRC has none: ``checked`` is False, and recovery trusts it least)."""

    schemas: list[Schema]
    channels: list[Channel]
    checked: bool


def decode(record: Metadata) -> ChannelCopy | None:
    """The copy a ``platoon.channels`` record holds; None if it does not decode, or its CRC-32 does not check."""
    try:
        crc = record.metadata.get("crc32")
        if crc is not None and crc != _crc(record.metadata["schemas"], record.metadata["channels"]):
            return None
        schemas = [Schema(id=int(s["id"]), name=str(s["name"]), encoding=str(s["encoding"]),
                          data=base64.b64decode(s["data"], validate=True)) for s in json.loads(record.metadata["schemas"])]
        channels = [Channel(id=int(c["id"]), schema_id=int(c["schema_id"]), topic=str(c["topic"]),
                            message_encoding=str(c["message_encoding"]),
                            metadata={str(k): str(v) for k, v in dict(c["metadata"]).items()})
                    for c in json.loads(record.metadata["channels"])]
    except (KeyError, TypeError, ValueError):
        return None
    return ChannelCopy(schemas, channels, crc is not None)
