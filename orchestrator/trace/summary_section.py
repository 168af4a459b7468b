"""A finished trace without its chunks decoded: that both ends are there, its metadata records (through the
summary section's index), and whether its data section is intact (the CRC-32 the writer records in the
DataEnd record, orchestrator/trace/mcap_file.py).

`platoon report` of a trace that stores its run's summary (orchestrator/analysis/stored_summary.py) reads
only this: no numpy, no decoding. The data section's CRC still covers every byte of the chunks and the
metadata, so a damaged trace is found as when every chunk is decoded (and the full reading then says where).
"""

from __future__ import annotations

import struct
import zlib
from pathlib import Path
from typing import Any, BinaryIO

from .format import FOOTER_LENGTH, MAGIC, TraceError

DATA_END = 0x0F  # the DataEnd record's opcode; its body is the data section's CRC-32 (4 bytes)
DATA_END_LENGTH = 1 + 8 + 4
_FOOTER = struct.Struct("<BQQQI")
_DATA_END = struct.Struct("<BQI")
READ_SIZE = 1 << 22  # bytes read at a time for the CRC: memory stays bounded on a long run's trace


def check_ends(path: Path, stream: BinaryIO) -> None:
    """Both magics and room for a footer, else a TraceError saying what to do (`platoon trace recover`)."""
    size = path.stat().st_size
    head = stream.read(len(MAGIC))
    stream.seek(max(0, size - len(MAGIC)))
    tail = stream.read(len(MAGIC))
    stream.seek(0)
    if head != MAGIC:
        raise TraceError("not an MCAP file (no MCAP magic at its start)")
    if tail != MAGIC or size < 2 * len(MAGIC) + FOOTER_LENGTH:
        raise TraceError(f"unfinished MCAP file (no footer: the writing process was killed?); "
                         f"recover its complete chunks with `platoon trace recover {path}`")


def finished_metadata(path: Path) -> tuple[dict[str, dict[str, str]], int]:
    """Every metadata record of a finished trace, by name, and where its summary section starts (0: none).
    Raises TraceError (or the reader's own error on a damaged summary)."""
    from mcap.reader import make_reader

    with open(path, "rb") as stream:
        check_ends(path, stream)
        stream.seek(-(FOOTER_LENGTH + len(MAGIC)), 2)
        opcode, _, summary_start, _, _ = _FOOTER.unpack(stream.read(FOOTER_LENGTH))
        if opcode != 0x02 or summary_start == 0:
            raise TraceError("no summary section")
        return metadata_records(make_reader(stream, validate_crcs=True)), summary_start


def metadata_records(reader: Any) -> dict[str, dict[str, str]]:
    """Every metadata record an mcap reader finds (through the summary's index where there is one), by name."""
    return {item.name: dict(item.metadata) for item in reader.iter_metadata()}


def data_section_intact(path: Path, summary_start: int) -> bool | None:
    """Whether the bytes before the DataEnd record (just before the summary, at ``summary_start``) match the
    CRC-32 it holds; None when its writer recorded none (0: an older trace, another writer)."""
    if summary_start < len(MAGIC) + DATA_END_LENGTH:
        return False
    with open(path, "rb") as stream:
        stream.seek(summary_start - DATA_END_LENGTH)
        opcode, length, recorded = _DATA_END.unpack(stream.read(DATA_END_LENGTH))
        if opcode != DATA_END or length != 4:
            return False
        if recorded == 0:
            return None
        stream.seek(0)
        left, crc = summary_start - DATA_END_LENGTH, 0
        while left > 0:
            block = stream.read(min(READ_SIZE, left))
            if not block:
                return False
            crc, left = zlib.crc32(block, crc), left - len(block)
    return crc == recorded
