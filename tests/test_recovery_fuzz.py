"""`trace recover` keeps every intact chunk, wherever the damage is.

A seeded campaign over a real 20 s trace written by `platoon run`, finished and unfinished (cut before
its summary, as a killed run leaves it): files cut at a random offset, with random bytes replaced,
with a random range overwritten, and combinations. A chunk of the original is *intact* when its bytes
are all still there, unchanged, at their offset. It counts as *kept* when the recovered file holds
every one of its messages (topic, log time, payload), up to the time the recovered file ends (recovery
trims to the last communication point every component reached). The campaign asserts 100 % kept and
prints the numbers (docs/trace-format.md, "Recovering").
"""

from __future__ import annotations

import random
import struct
from dataclasses import dataclass
from pathlib import Path

import pytest
from mcap.reader import make_reader
from mcap.records import Message

from orchestrator.trace.format import TraceError, channel_kind
from orchestrator.trace.recovery import _parse, recover
from tests.test_hostile_traces import reference  # noqa: F401 (the fixture: a completed 20 s paper run)

CASES = 60
SEED = 30


@dataclass(frozen=True)
class Chunk:
    start: int
    end: int
    messages: frozenset[tuple[str, int, bytes]]


def chunks_of(path: Path) -> tuple[list[Chunk], int, set[str]]:
    """Every chunk of ``path`` with its messages, where its data section ends (its DataEnd record), and
    the topics of its components (each row has one message on each)."""
    data = path.read_bytes()
    with open(path, "rb") as stream:
        summary = make_reader(stream).get_summary()
        topics = {cid: channel.topic for cid, channel in summary.channels.items()}
        components = {c.topic for c in summary.channels.values()
                      if channel_kind(c, summary.schemas.get(c.schema_id)) == "component"}
        chunks = []
        for index in summary.chunk_indexes:
            parsed = _parse(stream, index.chunk_start_offset, len(data))
            assert parsed is not None
            messages = frozenset((topics[m.channel_id], m.log_time, bytes(m.data)) for m in parsed[2] if isinstance(m, Message))
            chunks.append(Chunk(index.chunk_start_offset, index.chunk_start_offset + index.chunk_length, messages))
    return chunks, summary_start(data), components


def summary_start(data: bytes) -> int:
    """Where the data section ends: the DataEnd record (13 bytes) just before the summary the footer names."""
    footer = len(data) - 8 - (1 + 8 + 20)  # the footer record, then the closing magic
    assert data[footer] == 0x02
    return struct.unpack_from("<Q", data, footer + 9)[0] - 13


def damage(data: bytes, rng: random.Random) -> tuple[bytes, str]:
    """One seeded damage: a cut, flipped bytes, an overwritten range, or a mix of them."""
    out = bytearray(data)
    kinds = rng.choice([("cut",), ("flip",), ("overwrite",), ("flip", "overwrite"), ("overwrite", "cut"),
                        ("flip", "flip", "cut")])
    for kind in kinds:
        if kind == "flip":
            for _ in range(rng.randint(1, 4)):
                at = rng.randrange(8, len(out))
                out[at] ^= rng.randint(1, 255)
        elif kind == "overwrite":
            at = rng.randrange(8, len(out))
            length = rng.choice([rng.randint(1, 64), rng.randint(64, 8192), rng.randint(8192, len(out) // 4)])
            out[at:at + length] = bytes(rng.getrandbits(8) for _ in range(min(length, len(out) - at)))
        else:
            del out[rng.randrange(8, len(out)):]
    return bytes(out), "+".join(kinds)


def recovered_messages(path: Path) -> set[tuple[str, int, bytes]]:
    with open(path, "rb") as stream:
        return {(channel.topic, message.log_time, bytes(message.data))
                for _, channel, message in make_reader(stream).iter_messages()}


def complete_until(survivors: list[Chunk], components: set[str]) -> int | None:
    """The last time every component reached in the intact chunks: recovery may trim after it, not before."""
    last: dict[str, int] = {}
    for chunk in survivors:
        for topic, stamp, _ in chunk.messages:
            if topic in components:
                last[topic] = max(last.get(topic, stamp), stamp)
    return min(last.values()) if len(last) == len(components) else None


# the default run: the campaign's first 12 cases (the same seed, so the same files); the whole campaign
# (the numbers docs/trace-format.md gives) is a slow test: pytest -m slow -s tests/test_recovery_fuzz.py
@pytest.mark.parametrize("campaign", [12, pytest.param(CASES, marks=pytest.mark.slow)])
def test_recover_keeps_every_intact_chunk_of_randomly_damaged_traces(reference: Path, tmp_path: Path,  # noqa: F811
                                                                     campaign: int) -> None:
    finished = reference.read_bytes()
    chunks, data_end, components = chunks_of(reference)
    sources = {"finished": finished, "unfinished": finished[:data_end]}  # a killed run: no DataEnd, no summary
    rng = random.Random(SEED)
    intact = kept = cases = 0
    misses = []
    first = chunks[0]
    for case in range(campaign):
        name = "finished" if case % 2 == 0 else "unfinished"
        if case < 2:  # the worst single flip: one byte of the first chunk (which holds its chunk group's channels) flipped
            damaged, how = bytearray(sources[name]), "flip in the first chunk"
            damaged[(first.start + first.end) // 2] ^= 0x10
            damaged = bytes(damaged)
        else:
            damaged, how = damage(sources[name], rng)
        survivors = [c for c in chunks if c.end <= len(damaged) and damaged[c.start:c.end] == finished[c.start:c.end]]
        path, fixed = tmp_path / f"{case}.mcap", tmp_path / f"{case}-fixed.mcap"
        path.write_bytes(damaged)
        try:
            result = recover(path, fixed)
        except TraceError:
            assert not survivors, (case, name, how, "refused although chunks are intact")
            continue
        cases += 1
        end = complete_until(survivors, components)
        recovered_end = None if result.last_time is None else round(result.last_time * 1e9)
        assert end is None or (recovered_end is not None and recovered_end >= end), (case, name, how, end, recovered_end)
        messages = recovered_messages(fixed)
        for chunk in survivors:
            intact += 1
            wanted = {m for m in chunk.messages if end is not None and m[1] <= end}  # all but a last part row
            if wanted <= messages:
                kept += 1
            else:
                misses.append((case, name, how, chunk.start, len(wanted - messages)))
    print(f"\nrecovery fuzz (seed {SEED}, {campaign} damaged traces, {len(chunks)} chunks each): "
          f"{kept} of {intact} intact chunks kept ({100 * kept / max(intact, 1):.1f} %), {cases} recovered")
    assert not misses, misses
    assert intact > campaign * len(chunks) // 4  # the campaign damages some chunks, not all of them
