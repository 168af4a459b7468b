"""Reading traces back fast: ``load`` gives bit for bit what an independent reader (the mcap library's own
reader, every message through Python's json) gives, with the C decoder and without it, for whole traces,
time windows and chosen components, for hostile JSON and for files other writers made; memory stays
within twice the arrays it returns."""

from __future__ import annotations

import json
import math
import random
import shutil
import struct
import subprocess
import sys
import tracemalloc
from pathlib import Path

import numpy as np
import pytest

from orchestrator.execution.run import run_scenario
from orchestrator.scenario.config import load_config
from orchestrator.trace import TraceError, load
from orchestrator.trace import columns
from orchestrator.trace.columns import flatten

REPO = Path(__file__).resolve().parents[1]
STUDY = REPO / "configs" / "study" / "string_stability.toml"


def reference(path: Path) -> tuple[dict[str, dict[str, np.ndarray]], dict[str, np.ndarray], list[bytes]]:
    """Components (and live streams), errors and log payloads as the mcap library reads them, each
    message through Python's json: what ``load`` returned before it had a decoder of its own."""
    from mcap.reader import make_reader

    records: dict[str, list[dict]] = {}
    logs: list[bytes] = []
    with open(path, "rb") as stream:
        for _, channel, message in make_reader(stream).iter_messages(log_time_order=True):
            if channel.message_encoding == "json":
                record = json.loads(message.data)
                records.setdefault(channel.topic, []).append(flatten(record))
            elif channel.topic == "/platoon/log":
                logs.append(message.data)
    out = {}
    for topic, rows in records.items():
        out[topic] = {key: np.array([row[key] for row in rows], dtype=float) for key in rows[0]}
    errors = out.pop("/platoon/errors", {})
    return {topic[len("/platoon/"):]: value for topic, value in out.items()}, errors, logs


def same_bits(a: np.ndarray, b: np.ndarray) -> bool:
    return a.dtype == b.dtype == np.float64 and a.shape == b.shape and np.array_equal(a.view(np.uint64), b.view(np.uint64))


def assert_loads_as_reference(path: Path) -> None:
    components, errors, logs = reference(path)
    trace = load(path)
    read = {**trace.channels, **trace.live}
    assert set(read) == set(components)
    for name, expected in components.items():
        assert list(read[name]) == list(expected), name
        for key, values in expected.items():
            assert same_bits(read[name][key], values), f"{name}.{key}"
    assert list(trace.errors) == list(errors)
    for key, values in errors.items():
        assert same_bits(trace.errors[key], values), key
    assert len(trace.log) == len(logs)


@pytest.fixture(scope="module")
def lossy(tmp_path_factory: pytest.TempPathFactory, fmu_dir: Path) -> Path:
    """The string-stability study's cacc run with a delayed, lossy link, 60 s: every kind of JSON channel
    the writer makes (vehicles, target, links, errors) and the log."""
    config, text = load_config(STUDY, ["platoon.speed_law=cacc", "links.delay=0.3", "links.loss=0.2",
                                       "simulation.stop_time=60"])
    out = tmp_path_factory.mktemp("read") / "lossy.mcap"
    result = run_scenario(config, text, out, fmu_dir=fmu_dir)
    assert result.status == "completed", result.error
    return out


@pytest.fixture(params=["c", "python"])
def decoder(request, monkeypatch) -> str:
    """Each test twice: with the C decoder, and with the Python one a machine without a compiler uses."""
    if request.param == "c":
        if not columns.native_available():
            pytest.skip("the C decoder is not built (no C compiler at install time)")
    else:
        monkeypatch.setattr(columns, "_decode", None)
    return request.param


def test_the_c_decoder_is_built_where_a_compiler_is() -> None:
    if shutil.which("cc") is None and shutil.which("gcc") is None:
        pytest.skip("no C compiler on this machine: traces are read by the Python decoder")
    assert columns.native_available(), "a C compiler is here but orchestrator.trace._decode was not built"


def test_a_run_loads_bit_for_bit_as_the_reference_reader(lossy: Path, decoder: str) -> None:
    assert_loads_as_reference(lossy)


def test_a_window_and_components_are_the_whole_load_cut(lossy: Path, decoder: str) -> None:
    whole = load(lossy)
    part = load(lossy, components=["vehicle2", "target"], start=10.0, end=12.5, errors=False)
    assert list(part.channels) == ["target", "vehicle2"] and part.errors == {}
    assert part.window == (10.0, 12.5)
    for name in ("target", "vehicle2"):
        t = whole.channels[name]["t"]
        inside = (t >= 10.0) & (t <= 12.5)
        assert inside.sum() == 126  # 10.0, 10.02, ..., 12.5 at the study's 0.02 s step: both ends kept
        for key, values in whole.channels[name].items():
            assert same_bits(part.channels[name][key], values[inside]), f"{name}.{key}"
    assert [line.message for line in part.log] == []  # the log's lines are at 0 s and 60 s
    opened = load(lossy, start=59.0)
    assert opened.channels["vehicle1"]["t"][0] == 59.0 and opened.log[-1].message.startswith("run completed")


def test_bad_selections_are_named(lossy: Path) -> None:
    with pytest.raises(TraceError, match=r"no component vehicle9 in this trace \(it has .*vehicle7"):
        load(lossy, components=["vehicle9"])
    with pytest.raises(TraceError, match="the time window is empty"):
        load(lossy, start=5.0, end=4.0)


def test_a_window_reads_only_the_chunks_that_hold_it(lossy: Path, monkeypatch) -> None:
    read: list[int] = []
    original = columns.read_chunk

    def counting(stream, offset):
        read.append(offset)
        return original(stream, offset)

    monkeypatch.setattr(columns, "read_chunk", counting)
    load(lossy)
    every = len(read)
    read.clear()
    load(lossy, start=15.0, end=15.0)
    assert every >= 8 and 1 <= len(read) <= 2, (every, read)


# --- files the reader must take as Python's json takes them -------------------------------------------

def write_trace(path: Path, messages: list[tuple[str, int, bytes]], compression: str = "zstd", chunked: bool = True,
                kinds: bool = True) -> None:
    from mcap.writer import CompressionType, Writer

    with open(path, "wb") as stream:
        writer = Writer(stream, compression=CompressionType[compression.upper()], use_chunking=chunked,
                        chunk_size=4096)
        writer.start()
        channels: dict[str, int] = {}
        for topic, log_time, data in messages:
            if topic not in channels:
                schema = writer.register_schema(topic.replace("/", "."), "jsonschema", b'{"type":"object"}')
                kind = "errors" if topic.endswith("errors") else "component"
                channels[topic] = writer.register_channel(topic, "json", schema,
                                                          metadata={"platoon.kind": kind} if kinds else {})
            writer.add_message(channels[topic], log_time, data, log_time)
        writer.finish()


def number_texts(rng: random.Random) -> list[str]:
    """Number texts any JSON writer may have written: shortest, 17 digits, exponents, integers, zeros,
    subnormals, the largest and smallest doubles, long digit strings."""
    texts = ["0", "-0", "0.0", "-0.0", "1E5", "1e+5", "-2.5e-3", "12345678901234567890123", "1.7976931348623157e308",
             "5e-324", "2.2250738585072014e-308", "4.9406564584124654e-324", "9007199254740993", "0.1",
             "123456789012345678.5", "1e22", "1e23", "3.0e-22", "0.000000000000000000000000000001"]
    for _ in range(400):
        x = rng.choice([rng.uniform(-1e3, 1e3), rng.lognormvariate(0, 40) * rng.choice([-1, 1]),
                        struct.unpack("<d", struct.pack("<Q", rng.getrandbits(62)))[0]])
        texts += [repr(x), f"{x:.17g}", f"{x:.15e}", f"{x:.3f}"]
    return [t for t in texts if math.isfinite(float(t))]


def test_every_number_text_reads_as_pythons_float(tmp_path: Path, decoder: str) -> None:
    texts = number_texts(random.Random(41))
    messages = [("/platoon/target", k, f'{{"t":{k},"x":{text}}}'.encode()) for k, text in enumerate(texts)]
    write_trace(tmp_path / "numbers.mcap", messages)
    assert_loads_as_reference(tmp_path / "numbers.mcap")


def test_long_digits_and_ties_read_as_pythons_float(tmp_path: Path, decoder: str) -> None:
    """16 to 19 significant digits within 1e±27 of an integer: the C decoder's extended-precision path, and
    the decimal points exactly halfway between two doubles (and their neighbours), which that path hands
    to strtod so that ties round to even."""
    from decimal import Decimal

    rng = random.Random(57)
    texts = []
    for _ in range(600):
        x = rng.uniform(-1e3, 1e3) * 10.0 ** rng.randint(-27, 27)
        y = math.nextafter(x, math.inf)
        half = (Decimal(x) + Decimal(y)) / 2  # exact: the point where rounding turns from x to y
        texts += [repr(x), f"{x:.17g}", f"{x:.19g}", f"{half:.15e}", f"{half:.17e}", f"{half:.18e}"]
    texts += ["9007199254740993", "9007199254740995", "1.7976931348623157e27", "123456789012345678e-27"]
    messages = [("/platoon/target", k, f'{{"t":{k},"x":{text}}}'.encode()) for k, text in enumerate(texts)]
    write_trace(tmp_path / "ties.mcap", messages)
    read = load(tmp_path / "ties.mcap").component("target")["x"]
    assert [struct.pack("<d", value) for value in read] == [struct.pack("<d", float(text)) for text in texts]


def test_messages_unlike_the_first_are_read_as_json_reads_them(tmp_path: Path, decoder: str) -> None:
    messages = [
        ("/platoon/vehicle1", 0, b'{"t":0.0,"x":1.5,"gap":75.0}'),
        ("/platoon/vehicle1", 1, b'{"t": 0.01, "x": 1.25, "gap": 74.5}'),  # spaces
        ("/platoon/vehicle1", 2, b'{"x":1.0,"t":0.02,"gap":74.0}'),  # another key order
        ("/platoon/vehicle1", 3, b'{"t":0.03,"x":NaN,"gap":-Infinity}'),  # what Python's json writes for them
        ("/platoon/vehicle1", 4, b'{"t":0.04,"x":1.0,"gap":74.0,"extra":1}'),  # a key more (ignored, as before)
        ("/platoon/vehicle1", 5, b'{"t":0.05,"x":1e400,"gap":-0}'),
        ("/platoon/errors", 0, b'{"t":0.0,"vehicle1":{"path_error":-0.0,"gap_error":1e-7}}'),
        ("/platoon/errors", 1, b'{"t":0.01,"vehicle1":{"gap_error":2e-7,"path_error":0.5}}'),
        ("/platoon/weird", 0, rb'{"t":0.0,"a\"b":2.0,"c\\":3,"1.5":-1}'),  # escapes and numbers in keys
        ("/platoon/weird", 1, rb'{"t":0.01,"a\"b":2.5,"c\\":4,"1.5":-2}'),
    ]
    write_trace(tmp_path / "odd.mcap", messages)
    assert_loads_as_reference(tmp_path / "odd.mcap")


def test_a_message_that_is_no_row_is_a_damaged_trace(tmp_path: Path, decoder: str) -> None:
    for bad in (b'{"t":0.01,"x":"text"}', b'{"t":0.01}', b'[1, 2]', b'{"t":0.01,"x":1.0'):
        write_trace(tmp_path / "bad.mcap", [("/platoon/target", 0, b'{"t":0.0,"x":1.0}'), ("/platoon/target", 1, bad)])
        with pytest.raises(TraceError, match="recover"):
            load(tmp_path / "bad.mcap")


def test_out_of_order_messages_come_back_in_time_order(tmp_path: Path, decoder: str) -> None:
    times = [0, 30, 10, 20, 20, 40]
    messages = [("/platoon/target", t, f'{{"t":{t},"x":{k}.0}}'.encode()) for k, t in enumerate(times)]
    write_trace(tmp_path / "order.mcap", messages)
    target = load(tmp_path / "order.mcap").component("target")
    assert target["t"].tolist() == [0, 10, 20, 20, 30, 40] and target["x"].tolist() == [0, 2, 3, 4, 1, 5]


@pytest.mark.parametrize("compression, chunked", [("lz4", True), ("none", True), ("zstd", False)])
def test_other_writers_files_load(tmp_path: Path, decoder: str, compression: str, chunked: bool) -> None:
    rng = random.Random(7)
    messages = []
    for k in range(300):
        for topic in ("/platoon/target", "/platoon/vehicle1"):
            messages.append((topic, k * 10_000_000, json.dumps({"t": k * 0.01, "x": rng.gauss(0, 50)}).encode()))
    write_trace(tmp_path / "other.mcap", messages, compression, chunked, kinds=False)
    assert_loads_as_reference(tmp_path / "other.mcap")


def test_a_chunk_that_fails_its_crc_is_named(lossy: Path, tmp_path: Path) -> None:
    from mcap.reader import make_reader

    with open(lossy, "rb") as stream:
        summary = make_reader(stream).get_summary()
    # the third chunk of the vehicles' (a load reads it; another chunk group's, the scene's, it need not)
    chunk = [c for c in sorted(summary.chunk_indexes, key=lambda c: c.chunk_start_offset)
             if any(summary.channels[cid].topic == "/platoon/vehicle1" for cid in c.message_index_offsets)][2]
    data = bytearray(lossy.read_bytes())
    data[chunk.chunk_start_offset + chunk.chunk_length - 100] ^= 0xFF
    broken = tmp_path / "broken.mcap"
    broken.write_bytes(bytes(data))
    with pytest.raises(TraceError, match=r"damaged MCAP file.*platoon trace recover"):
        load(broken)


def test_load_holds_at_most_twice_the_arrays_it_returns(lossy: Path) -> None:
    """Peak memory of a load (numpy's and Python's allocations, traced) against the arrays it returns:
    each value is written once into its final column, so what is held beyond them is a chunk or two."""
    tracemalloc.start()
    try:
        trace = load(lossy)
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    arrays = sum(a.nbytes for group in (*trace.channels.values(), trace.errors) for a in group.values())
    assert arrays > 4 << 20  # a trace large enough that a chunk or two of overhead is small beside it
    assert peak <= 2 * arrays, (peak, arrays)


def test_components_by_a_test_of_their_name(lossy: Path) -> None:
    from orchestrator.trace.format import is_link

    whole = load(lossy)
    bodies = load(lossy, components=lambda name: not is_link(name), errors=False)
    assert list(bodies.channels) == [name for name in whole.channels if not is_link(name)] and bodies.errors == {}
    assert all(same_bits(bodies.channels[n][k], whole.channels[n][k]) for n in bodies.channels for k in whole.channels[n])


def test_the_readback_benchmark_writes_its_ratios(tmp_path: Path) -> None:
    platoon = Path(sys.executable).parent / "platoon"
    done = subprocess.run([str(platoon), "bench", "readback", "--rounds", "1", "-q", "--out-dir", str(tmp_path)], cwd=REPO,
                          capture_output=True, text=True, timeout=900)
    assert done.returncode == 0, done.stderr
    result = json.loads(next(tmp_path.glob("readback-*.json")).read_text())
    medians = result["medians"]
    assert {"study run", "study load", "study stability", "readme run", "readme report"} <= set(medians)
    assert 0 < medians["study load"]["slice"] < medians["study load"]["whole"]
    assert medians["study memory"]["arrays"] > 20 << 20  # the study trace's columns: 10 284 rows, 23 channels
    assert "reader / writer" in done.stdout


def test_mutated_chunks_are_read_or_refused_never_a_crash(lossy: Path, decoder: str) -> None:
    """Chunk contents a hostile file can carry past its CRC (the CRC is the file's own): random bytes in the
    records and the JSON, cut at record boundaries; each chunk decodes or is refused with an error naming it."""
    from mcap.reader import make_reader

    with open(lossy, "rb") as stream:
        summary = make_reader(stream).get_summary()
        first = min((chunk for chunk in summary.chunk_indexes  # the vehicles' first chunk: JSON records
                     if any(summary.channels[cid].topic == "/platoon/vehicle1" for cid in chunk.message_index_offsets)),
                    key=lambda chunk: chunk.chunk_start_offset)
        records = columns.read_chunk(stream, first.chunk_start_offset)
    bounds, at = [], 0
    while at < len(records) and len(bounds) < 400:
        at += 9 + struct.unpack_from("<BQ", records, at)[1]
        bounds.append(at)
    json_channels = [cid for cid, ch in summary.channels.items() if ch.message_encoding == "json"]
    rng = random.Random(43)
    outcomes = {"read": 0, "refused": 0}
    for _ in range(300):
        data = bytearray(records[:rng.choice(bounds)])
        for _ in range(rng.randrange(1, 12)):
            data[rng.randrange(len(data))] = rng.choice([rng.randrange(256), *b'"\\-0e.{', 0])
        slots = {cid: columns.JsonColumns(str(cid), False, rng.choice([0, 1, 100])) for cid in json_channels}
        try:
            columns.ChunkDecoder(slots).chunk(bytes(data))
            for slot in slots.values():
                slot.columns()
            outcomes["read"] += 1
        except (TraceError, ValueError, KeyError, TypeError):
            outcomes["refused"] += 1
    assert outcomes["read"] > 30 and outcomes["refused"] > 30, outcomes
