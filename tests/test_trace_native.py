"""The trace encoded in C (orchestrator/trace/native_encoder.c) writes what the Python encoder writes.

The Python encoder (``ComponentMessages``, ``FoxgloveChannels``) is the reference. The same float64
rows go through both and the files are compared byte for byte and, read back by the ``mcap``
library (a reader that shares no code with either encoder), message by message: topic, log and
publish time, sequence, and the decoded message (JSON values bit for bit, the scene and transforms
decoded as protobuf). Whole runs compare the native engine (C encoder) with the Python engine
(Python encoder), which step the same doubles.
"""

from __future__ import annotations

import json
import math
import random
import struct
from pathlib import Path

import numpy as np
import orjson
import pytest

from fmus.errors import ComponentError
from orchestrator.components.kinds import native_buildable
from orchestrator.scenario.config import load_config
from orchestrator.execution.run import run_scenario
from orchestrator.trace import TraceWriter, load
from orchestrator.trace.foxglove import FoxgloveChannels
from orchestrator.trace.native_rows import available
from tests.conftest import SPEED_TO_ZERO

REPO = Path(__file__).resolve().parents[1]
PAPER = REPO / "configs" / "paper" / "platoon.toml"



def why_not_built() -> str:
    """Why ``orchestrator.trace._native`` does not import (native_rows swallows the ImportError)."""
    import importlib

    try:
        importlib.import_module("orchestrator.trace._native")
    except ImportError as error:
        return str(error)
    return "it imports now, though native_rows found it missing"


@pytest.fixture(autouse=True)
def the_c_encoder() -> None:
    """Every test here needs the C encoder: without a C compiler it cannot be built (the Python encoder
    writes every row) and the tests skip; with one, an encoder that did not build is a failure, whatever
    the reason (a compile error in native_encoder.c, a broken install), not a skip."""
    if available():
        return
    if not native_buildable():
        pytest.skip("no C compiler: the C trace encoder is not built (the Python encoder writes every row)")
    pytest.fail(f"a C compiler is here, but the C trace encoder is not built ({why_not_built()}); "
                "`pip install -e .` shows why", pytrace=False)


def paper(*overrides: str):
    config, _ = load_config(PAPER, list(overrides))
    return config


_CLASSES: dict[tuple[str, bytes], object] = {}  # one protobuf class per schema, so that messages of two files compare


def decoded(path: Path) -> list[tuple]:
    """Every message of a trace in file order, decoded: (topic, log time, publish time, sequence, content)."""
    from google.protobuf import descriptor_pb2, descriptor_pool, message_factory
    from mcap.reader import make_reader

    classes = _CLASSES
    out = []
    with open(path, "rb") as stream:
        reader = make_reader(stream, validate_crcs=True)
        for schema, channel, message in reader.iter_messages(log_time_order=False):
            if channel.message_encoding == "json":
                content = json.loads(message.data)
            else:
                key = (schema.name, bytes(schema.data))
                if key not in classes:
                    pool = descriptor_pool.DescriptorPool()
                    for file in descriptor_pb2.FileDescriptorSet.FromString(schema.data).file:
                        pool.Add(file)
                    classes[key] = message_factory.GetMessageClass(pool.FindMessageTypeByName(schema.name))
                content = classes[key].FromString(message.data)
            out.append((channel.topic, message.log_time, message.publish_time, message.sequence, content))
    return out


def assert_same_messages(reference: Path, native: Path) -> int:
    """Message by message, decoded; returns how many."""
    expected, got = decoded(reference), decoded(native)
    assert len(expected) == len(got)
    for index, (a, b) in enumerate(zip(expected, got)):
        assert a[:4] == b[:4], index
        if isinstance(a[4], dict):  # JSON numbers bit for bit (== would let 0.0 and -0.0 pass)
            assert json.dumps(a[4]) == json.dumps(b[4]), (index, a[0])
        else:
            assert a[4] == b[4], (index, a[0])
    return len(expected)


# --- numbers ------------------------------------------------------------------------------------

def test_numbers_are_written_as_orjson_writes_them() -> None:
    """format_double against orjson (the Python encoder's number texts): the exact-integer path
    (1e-22 <= |x| < 2^53), the repr path elsewhere, the notation switches at 1e-5 and 1e16."""
    from orchestrator.trace import _native

    rng = random.Random(31)
    values = [0.0, -0.0, 1.0, 25.0, 100.0, 0.1, 1e-5, 9.99e-6, 1e-6, 1e15, 1e16, 9999999999999998.0, 2.0**52,
              2.0**53, 2.0**53 - 1, 4503599627370496.5, 5e-324, 2.2250738585072014e-308, 1.7976931348623157e308]
    for _ in range(60_000):
        bits = struct.unpack("<d", struct.pack("<Q", rng.getrandbits(64)))[0]
        if math.isfinite(bits):
            values.append(bits)  # every exponent
        values.append(rng.uniform(-200.0, 200.0))  # this project's magnitudes
        values.append(rng.uniform(-1.0, 1.0) * 10.0 ** rng.randint(-8, 17))
        values.append(rng.uniform(-1.0, 1.0) * 10.0 ** rng.randint(-25, -4))  # small: the 192-bit products
        values.append(round(rng.uniform(-100.0, 100.0), rng.randint(0, 6)))  # short decimals
        values.append(math.nextafter(10.0 ** rng.randint(-24, 17), rng.choice((0.0, math.inf))))  # around powers of ten
    mismatches = [v for v in values if _native.format_double(v) != orjson.dumps(v)]
    assert mismatches == []


# --- the writer: same rows, both encoders ---------------------------------------------------------

def _rows(config, components: list[tuple[str, list[str]]], count: int, seed: int) -> np.ndarray:
    """Rows shaped like a run's: every component on the config's path, moving, with noise."""
    rng = np.random.default_rng(seed)
    width = 1 + sum(len(outputs) for _, outputs in components)
    rows = rng.normal(0.0, 30.0, (count, width))
    rows[rng.random(rows.shape) < 0.05] = 0.0  # zeros (left out of the protobuf, "0.0" in JSON)
    rows[:, 0] = np.arange(count) * config.simulation.step * config.simulation.trace_every
    rows[:, 5] *= 1e-9  # tiny values: the repr path
    return rows


def _write(path: Path, native: bool, config, components, rows: np.ndarray, chunk_size: int, block: int) -> TraceWriter:
    writer = TraceWriter(path, components, every=config.simulation.trace_every, native=native, flush_interval=1e9,
                         chunk_size=chunk_size, foxglove=FoxgloveChannels(config, components, scene_rate=7.0))
    assert writer.native == native
    writer.metadata("platoon.config", {"toml": "x"})
    writer.log(0.0, "Info", "run started")
    for start in range(0, len(rows), block):
        writer.write_block(rows[start:start + block])
    writer.log(float(rows[-1, 0]), "Info", "run completed")
    writer.close()
    return writer


COMPONENTS = {"target": ["x", "y", "heading", "speed", "curvature"],
              "vehicle": ["x", "y", "heading", "speed", "gap", "wheel.right", "50%", 'say "hi"']}


@pytest.mark.parametrize("overrides, count, chunk_size, block, links", [
    ((), 800, 1 << 20, 500, False),  # the paper's circle, four vehicles
    (("platoon.count=12", "path.kind=line", "path.heading=0.7", "path.center=[3.0, -2.0]"), 300, 1 << 14, 64, False),
    (("platoon.count=3", "path.direction=cw", "simulation.trace_every=7", "path.radius=20.0", "platoon.d_star=15.0"), 400, 1 << 16, 33, False),
    ((), 700, 1 << 15, 90, True),  # links between the vehicles: every chunk group, each in its chunks
])
def test_native_and_python_encoders_write_the_same_file(tmp_path: Path, overrides, count: int, chunk_size: int,
                                                        block: int, links: bool) -> None:
    """Byte for byte (many chunks, odd blocks, keys to escape, the chunk groups), hence message by message."""
    config = paper(*overrides)
    vehicles = [f"vehicle{k}" for k in range(1, config.platoon.count + 1)]
    components = [("target", COMPONENTS["target"])] + [(name, COMPONENTS["vehicle"]) for name in vehicles]
    if links:  # as a run orders them: each link after the vehicle it feeds
        components = [entry for name, outputs in components
                      for entry in [(name, outputs)] + ([(f"link_backward{name[7:]}", ["gap", "speed"])]
                                                         if name.startswith("vehicle") else [])]
    rows = _rows(config, components, count, seed=count)
    files = {}
    for native in (False, True):
        files[native] = tmp_path / f"{native}.mcap"
        writer = _write(files[native], native, config, components, rows, chunk_size, block)
        assert writer.recorded == count and writer.last_time == rows[-1, 0]
    assert files[True].read_bytes() == files[False].read_bytes()
    messages = assert_same_messages(files[False], files[True])
    topics = load(files[True]).topics
    scenes = topics["/platoon/scene"].messages
    assert topics["/platoon/tf"].messages == scenes
    assert abs(scenes - rows[-1, 0] * 7.0) <= 2  # 7 Hz of simulated time, from t = 0
    assert messages == count * (len(components) + 1) + 2 + 2 * scenes  # + the errors; two log lines
    if links:
        from mcap.reader import make_reader

        from orchestrator.trace.format import LINKS, chunk_group

        with open(files[True], "rb") as stream:
            summary = make_reader(stream).get_summary()
        groups = [{chunk_group(summary.channels[cid].topic) for cid in chunk.message_index_offsets}
                  for chunk in summary.chunk_indexes]
        assert all(len(group) == 1 for group in groups) and len(groups) > 6 and {LINKS} in groups


@pytest.mark.parametrize("flush_interval", [1e9, 0.0])  # chunks closed by size only, or by a flush after every block
def test_chunks_compressed_on_a_thread_give_the_same_file(tmp_path: Path, monkeypatch, flush_interval: float) -> None:
    """The writer compresses full chunks on a second thread (orchestrator/trace/chunks.py): the file is byte
    for byte the one written when the writer's own thread compresses every chunk, metadata and log lines
    written between chunks still waiting for their compression included."""
    import orchestrator.trace.writer as writer_module

    config = paper("platoon.count=6")
    components = [("target", COMPONENTS["target"])] + [(f"vehicle{k}", COMPONENTS["vehicle"]) for k in range(1, 7)]
    rows = _rows(config, components, 600, seed=5)
    files = {}
    for threaded in (True, False):
        if not threaded:
            monkeypatch.setattr(writer_module, "ChunkPipeline", lambda *arguments: None)
        files[threaded] = tmp_path / f"{threaded}.mcap"
        writer = TraceWriter(files[threaded], components, native=True, flush_interval=flush_interval,
                             chunk_size=1 << 13, foxglove=FoxgloveChannels(config, components))
        assert (writer._encoder._pipeline is not None) == threaded
        for start in range(0, len(rows), 50):
            writer.write_block(rows[start:start + 50])
            writer.metadata(f"block{start}", {"rows": str(start)})
            writer.log(float(rows[start, 0]), "Info", f"block {start}")
        writer.close()
    assert files[True].read_bytes() == files[False].read_bytes()
    assert len(decoded(files[True])) == 600 * (len(components) + 1) + 12 + 2 * load(files[True]).topics["/platoon/tf"].messages


def _refusals(tmp_path: Path, components, rows: np.ndarray, error: type[Exception]) -> dict[bool, tuple]:
    """Each encoder's (writer, error message, file bytes) after writing ``rows``, which must raise ``error``."""
    config = paper()
    outcomes = {}
    for native in (False, True):
        path = tmp_path / f"{native}.mcap"
        writer = TraceWriter(path, components, native=native, flush_interval=1e9,
                             foxglove=FoxgloveChannels(config, components))
        with pytest.raises(error) as failure:
            writer.write_block(rows)
        writer.close()
        outcomes[native] = (writer, str(failure.value), path.read_bytes())
    return outcomes


def test_a_non_finite_row_ends_the_native_trace_before_it(tmp_path: Path) -> None:
    components = [("target", COMPONENTS["target"])] + [(f"vehicle{k}", COMPONENTS["vehicle"]) for k in range(1, 5)]
    rows = _rows(paper(), components, 50, seed=1)
    rows[37, 9] = math.nan
    outcomes = _refusals(tmp_path, components, rows, ComponentError)
    for writer, _, _ in outcomes.values():
        assert writer.recorded == 37 and writer.last_time == rows[36, 0]
    assert "vehicle1 failed" in outcomes[True][1] and "output speed = nan is not finite" in outcomes[True][1]
    assert outcomes[True][1:] == outcomes[False][1:]


def test_a_non_finite_error_value_is_refused_like_the_python_encoder(tmp_path: Path) -> None:
    """Finite outputs whose path error overflows: both encoders stop before that row with the same ValueError."""
    components = [("target", COMPONENTS["target"]), ("vehicle1", COMPONENTS["vehicle"])]
    rows = _rows(paper(), components, 20, seed=2)
    rows[12, 6:8] = 1.7e308, -1.7e308  # vehicle1 far off the path: the row sums to a finite number, hypot overflows
    outcomes = _refusals(tmp_path, components, rows, ValueError)
    assert outcomes[True][1] == f"an error at t = {rows[12, 0]:g} s is not finite"
    assert outcomes[True][0].recorded == 12
    assert outcomes[True][1:] == outcomes[False][1:]


# --- whole runs: the native engine (C encoder) against the Python engine (Python encoder) ---------

def _same_run_messages(tmp_path: Path, fmu_dir: Path, config, text: str, writer: str) -> tuple[Path, Path]:
    files = {}
    for engine in ("python", "native"):
        files[engine] = tmp_path / f"{engine}.mcap"
        result = run_scenario(config, text, files[engine], engine=engine, fmu_dir=fmu_dir, trace_writer=writer)
        assert result.status == ("failed" if "disturbance" in text else "completed"), result.error
    assert load(files["native"]).metadata["platoon.start"]["trace_encoder"] == "native"
    assert load(files["python"]).metadata["platoon.start"]["trace_encoder"] == "python"
    expected, got = decoded(files["python"]), decoded(files["native"])
    assert len(expected) == len(got) > 0
    # the log's first line names the engine; everything else is the same message
    assert [m for m in expected if m[0] != "/platoon/log"] == [m for m in got if m[0] != "/platoon/log"]
    return files["python"], files["native"]


@pytest.mark.parametrize("overrides, writer", [
    (("simulation.stop_time=2.0",), "inline"),
    (("simulation.stop_time=3.0", "simulation.trace_every=7", "platoon.count=6"), "process"),
    (("simulation.stop_time=1.5", "path.kind=line"), "process"),
])
def test_native_engine_trace_is_the_python_engine_trace(tmp_path: Path, fmu_dir: Path, overrides, writer: str) -> None:
    config = paper("simulation.fmus=native", *overrides)
    _same_run_messages(tmp_path, fmu_dir, config, PAPER.read_text(), writer)


def test_a_run_failing_mid_way_traces_the_same_messages(tmp_path: Path, fmu_dir: Path) -> None:
    source = tmp_path / "speed_to_zero.toml"
    source.write_text(PAPER.read_text() + SPEED_TO_ZERO)
    config, _ = load_config(source, ["simulation.stop_time=2.0", "simulation.fmus=native"])
    _, native = _same_run_messages(tmp_path, fmu_dir, config, source.read_text(), "inline")
    trace = load(native)
    assert trace.run["status"] == "failed" and trace.run["error"].startswith("vehicle4 failed at t = 1 s")
    assert trace.component("vehicle4")["t"][-1] == pytest.approx(1.0)


@pytest.mark.skipif(not available(), reason="the C trace encoder is not built")
def test_the_non_finite_check_finds_the_first_bad_row_as_numpy_does() -> None:
    """The stepping process checks each block in C before shipping it (no numpy in a plain run): the row
    it names is numpy's, for nan, both infinities, in raw bytes and in a RowBlock."""
    from orchestrator.support.rows import RowBlock
    from orchestrator.trace import native_rows

    generator = np.random.default_rng(7)
    for _ in range(200):
        rows, width = int(generator.integers(1, 40)), int(generator.integers(1, 30))
        block = generator.normal(size=(rows, width)) * 10.0 ** generator.integers(-300, 300, size=(rows, width))
        for _ in range(int(generator.integers(0, 3))):
            block[generator.integers(rows), generator.integers(width)] = generator.choice([np.nan, np.inf, -np.inf])
        finite = np.isfinite(block).all(axis=1)
        expected = None if finite.all() else int(np.argmin(finite))
        assert native_rows.first_non_finite(block.tobytes(), width) == expected
        view = RowBlock.of(block)
        assert native_rows.first_non_finite(view.values, view.width) == expected
    with pytest.raises(ValueError, match="not whole rows of 4"):
        native_rows.first_non_finite(np.zeros(6).tobytes(), 4)


def test_an_encoder_that_did_not_build_fails_these_tests_where_a_compiler_exists() -> None:
    """The rule above, applied: a pytest process in which the extension cannot be imported (as after a
    failed build) fails this file's tests where a compiler exists, and skips them only where none does."""
    import subprocess
    import sys

    hide = ("import sys; sys.modules['orchestrator.trace._native'] = None; import pytest; "
            "sys.exit(pytest.main(['-q', '-n', '0', '-p', 'no:cacheprovider', sys.argv[1], '-k', "
            "'test_numbers_are_written_as_orjson_writes_them']))")
    result = subprocess.run([sys.executable, "-c", hide, __file__], cwd=REPO, capture_output=True, text=True,
                            timeout=300)
    if native_buildable():
        assert result.returncode == 1, result.stdout[-3000:]
        assert "a C compiler is here, but the C trace encoder is not built" in result.stdout, result.stdout[-3000:]
    else:
        assert result.returncode == 0 and "1 skipped" in result.stdout, result.stdout[-3000:]
