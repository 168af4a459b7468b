"""Traces as a product: Foxglove channels, read-back, CSV export, an independent reader,
nothing lost on SIGINT / SIGTERM / SIGKILL / FMU failure, decimation.

The signal tests run the installed ``platoon`` console script in a real subprocess on a long
scenario and signal it once its trace holds data. The independent check reads our files with
Foxglove's TypeScript ``@mcap/core`` under Node (tests/mcap_js), installed from the npm registry on
first use; it is skipped, saying why, only when npm cannot reach the registry.
"""

from __future__ import annotations

import csv
import fcntl
import json
import math
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from orchestrator.scenario.config import load_config
from orchestrator.trace.foxglove import ERRORS_TOPIC, LOG_TOPIC, SCENE_TOPIC, TF_TOPIC, layout_json
from orchestrator.components.fmu import ComponentError
from orchestrator.analysis.metrics import path_errors
from orchestrator.execution.run import run_scenario
from orchestrator.trace import Trace, TraceError, TraceWriter, export_csv, load, number_texts, recover
from orchestrator.trace.encoding import json_template
from tests.conftest import SPEED_TO_ZERO

REPO = Path(__file__).resolve().parents[1]
PLATOON = Path(sys.executable).parent / "platoon"
PAPER = REPO / "configs" / "paper" / "platoon.toml"
MCAP_JS = REPO / "tests" / "mcap_js"
COMPONENTS = ["target", "vehicle1", "vehicle2", "vehicle3", "vehicle4"]
VEHICLES = COMPONENTS[1:]
SHORT_STOP = 5.0


def paper(*overrides: str):
    config, _ = load_config(PAPER, list(overrides))
    return config


def env() -> dict[str, str]:
    out = {**os.environ, "COLUMNS": "80", "NO_COLOR": "1", "TERM": "dumb"}
    out.pop("FORCE_COLOR", None)
    return out


def platoon(*args: object, cwd: Path, timeout: float = 120) -> subprocess.CompletedProcess[str]:
    return subprocess.run([str(PLATOON), *map(str, args)], cwd=cwd, env=env(), capture_output=True, text=True,
                          timeout=timeout)


# --- a short run, read back ------------------------------------------------------------------------

@pytest.fixture(scope="module")
def short(tmp_path_factory: pytest.TempPathFactory, fmu_dir: Path) -> Trace:
    out = tmp_path_factory.mktemp("traces") / "short.mcap"
    result = run_scenario(paper(f"simulation.stop_time={SHORT_STOP}"), PAPER.read_text(), out, fmu_dir=fmu_dir)
    assert result.status == "completed", result.error
    return load(out)


def test_channels_schemas_and_counts(short: Trace) -> None:
    rows = int(round(SHORT_STOP / 0.01)) + 1
    expected = {f"/platoon/{name}": (f"platoon.{name}", "json", rows) for name in COMPONENTS}
    expected[ERRORS_TOPIC] = ("platoon.errors", "json", rows)
    scenes = int(round(SHORT_STOP * 10)) + 1  # 10 Hz of simulated time, t = 0 included
    expected[SCENE_TOPIC] = ("foxglove.SceneUpdate", "protobuf", scenes)
    expected[TF_TOPIC] = ("foxglove.FrameTransforms", "protobuf", scenes)
    expected[LOG_TOPIC] = ("foxglove.Log", "protobuf", 2)  # started, completed
    assert {t: (i.schema, i.message_encoding, i.messages) for t, i in short.topics.items()} == expected


def test_load_keeps_components_apart_from_derived_channels(short: Trace) -> None:
    assert list(short.channels) == COMPONENTS  # /platoon/errors, scene, tf and log are not components
    assert short.vehicles() == VEHICLES
    for name in COMPONENTS:
        t = short.component(name)["t"]
        assert t[0] == 0.0 and t[-1] == pytest.approx(SHORT_STOP) and np.all(np.diff(t) > 0)
    assert short.run["status"] == "completed"
    assert set(short.run) >= {"status", "error", "engine", "master", "steps_recorded"}
    assert short.run["steps_recorded"] == str(len(short.component("target")["t"]))
    assert [line.level for line in short.log] == ["Info", "Info"]
    assert short.log[0].t == 0.0 and short.log[-1].t == pytest.approx(SHORT_STOP)
    assert "run completed" in short.log[-1].message


def test_errors_channel_matches_the_path_and_config(short: Trace) -> None:
    config = paper(f"simulation.stop_time={SHORT_STOP}")
    errors = short.errors
    assert np.array_equal(errors["t"], short.component("target")["t"])
    for name in VEHICLES:
        channel = short.component(name)
        assert np.array_equal(errors[f"{name}.path_error"], path_errors(config, channel["x"], channel["y"]))
        assert np.array_equal(errors[f"{name}.gap_error"], channel["gap"] - config.platoon.d_star)
        assert np.array_equal(errors[f"{name}.speed_error"], channel["speed"] - config.platoon.speed)
    assert all(np.all(np.isfinite(column)) for column in errors.values())
    # vehicle 1 starts 5 m outside the circle (configs/paper/platoon.toml)
    assert errors["vehicle1.path_error"][0] == pytest.approx(5.0)


def _protobuf_messages(path: Path, topics: list[str]):
    """Decode Foxglove channels with the protobuf schemas stored in the file, as Foxglove does."""
    pytest.importorskip("google.protobuf")
    from google.protobuf import descriptor_pb2, descriptor_pool, message_factory
    from mcap.reader import make_reader

    classes = {}
    with open(path, "rb") as stream:
        for schema, channel, message in make_reader(stream, validate_crcs=True).iter_messages(topics=topics, log_time_order=True):
            if schema.id not in classes:
                pool = descriptor_pool.DescriptorPool()
                for file in descriptor_pb2.FileDescriptorSet.FromString(schema.data).file:
                    pool.Add(file)
                classes[schema.id] = message_factory.GetMessageClass(pool.FindMessageTypeByName(schema.name))
            yield channel.topic, message.log_time, classes[schema.id].FromString(message.data)


def test_scene_carries_the_whole_scene_in_a_defined_frame(short: Trace) -> None:
    scenes = transforms = 0
    for topic, log_time, message in _protobuf_messages(short.path, [SCENE_TOPIC, TF_TOPIC]):
        assert log_time % 100_000_000 == 0  # 10 Hz of simulated time
        if topic == TF_TOPIC:
            transforms += 1
            assert [(f.parent_frame_id, f.child_frame_id) for f in message.transforms] == [("world", n) for n in COMPONENTS]
            continue
        scenes += 1
        entities = {entity.id: entity for entity in message.entities}
        assert set(entities) == {"path", *COMPONENTS}  # every message: the path, the target, every vehicle
        assert {entity.frame_id for entity in message.entities} == {"world"}  # a frame /platoon/tf defines
        for entity in message.entities:
            stamp = entity.timestamp.seconds * 1_000_000_000 + entity.timestamp.nanos
            assert stamp == log_time
        assert len(entities["path"].lines[0].points) == 180
        radii = [math.hypot(p.x, p.y) for p in entities["path"].lines[0].points]
        assert max(abs(r - 50.0) for r in radii) < 1e-9
        for name in VEHICLES:
            vehicle = entities[name]
            assert len(vehicle.cubes) == 1 and len(vehicle.arrows) == 1 and vehicle.texts[0].text == name
            history = vehicle.lines[0].points
            assert 1 <= len(history) <= 50  # 5 s of simulated time at 10 Hz
            pose = vehicle.cubes[0].pose.position
            assert (history[-1].x, history[-1].y) == (pose.x, pose.y)
        assert len(entities["target"].spheres) == 1
    assert scenes == transforms == int(round(SHORT_STOP * 10)) + 1


def test_scene_poses_are_the_recorded_positions(short: Trace) -> None:
    x = dict(zip(np.round(short.component("vehicle2")["t"] * 1e9).astype(np.int64).tolist(), short.component("vehicle2")["x"]))
    for _, log_time, message in _protobuf_messages(short.path, [SCENE_TOPIC]):
        vehicle = next(e for e in message.entities if e.id == "vehicle2")
        assert vehicle.cubes[0].pose.position.x == x[log_time]


def test_layout_file_is_the_generated_classic_layout(short: Trace) -> None:
    text = (REPO / "layouts" / "platoon.json").read_text()
    assert text == layout_json(6), "regenerate: python -m orchestrator.trace.foxglove 6 > layouts/platoon.json"
    layout = json.loads(text)
    assert {"configById", "layout", "globalVariables"} <= set(layout)
    panels = layout["configById"]
    three_d = next(v for k, v in panels.items() if k.startswith("3D!"))
    assert three_d["topics"][SCENE_TOPIC]["visible"] is True
    plotted = {path["value"] for k, v in panels.items() if k.startswith("Plot!") for path in v["paths"]}
    for name in VEHICLES:  # every series of the 4-vehicle trace resolves to a column of /platoon/errors
        for field in ("path_error", "gap_error", "speed_error"):
            assert f"{ERRORS_TOPIC}.{name}.{field}" in plotted
            assert f"{name}.{field}" in short.errors

    def leaves(node):
        return [node] if isinstance(node, str) else leaves(node["first"]) + leaves(node["second"])

    assert sorted(leaves(layout["layout"])) == sorted(panels)  # the tree shows every configured panel


def test_export_csv(short: Trace, tmp_path: Path) -> None:
    files = export_csv(short, tmp_path)
    assert sorted(p.name for p in files) == sorted([f"{n}.csv" for n in COMPONENTS] + ["errors.csv"])
    for name in COMPONENTS:
        with open(tmp_path / f"{name}.csv", newline="") as stream:
            rows = list(csv.reader(stream))
        columns = short.component(name)
        assert rows[0] == list(columns)  # header: t, then the variable names
        assert rows[0][0] == "t"
        values = np.array([[float(v) for v in row] for row in rows[1:]])
        for i, key in enumerate(rows[0]):
            assert np.array_equal(values[:, i], columns[key])  # exact: repr round-trips


def test_json_encoding_is_exact_json() -> None:
    keys = ["t", "x", "wheel.right", 'odd"%name']
    for values in ([0.0, 1e-7, 1e22, -0.0], [5e-324, 1.7976931348623157e308, 0.1 + 0.2, -123.456],
                   [np.float64(1.25), 3, 2.5e-310, 1 / 3]):
        text = json_template(keys) % tuple(number_texts(list(values)))
        decoded = json.loads(text)
        assert list(decoded) == keys
        assert [float(decoded[k]).hex() for k in keys] == [float(v).hex() for v in values]  # bit for bit


def chunk_channels(path: Path) -> list[set[str]]:
    """The topics of each chunk of a finished trace, from its chunk indexes."""
    from mcap.reader import make_reader

    with open(path, "rb") as stream:
        summary = make_reader(stream).get_summary()
    return [{summary.channels[cid].topic for cid in chunk.message_index_offsets} for chunk in summary.chunk_indexes]


def same_arrays(a: Trace, b: Trace) -> bool:
    """Every component's and the errors' arrays the same, bit for bit, and the same log."""
    def bits(columns: dict[str, np.ndarray]) -> dict[str, bytes]:
        return {key: values.tobytes() for key, values in columns.items()}
    return ({name: bits(columns) for name, columns in a.channels.items()}
            == {name: bits(columns) for name, columns in b.channels.items()}
            and bits(a.errors) == bits(b.errors) and a.log == b.log)


def test_the_encoder_writes_the_messages_mcap_add_message_writes(tmp_path: Path, short: Trace) -> None:
    """The encoder frames Message records into its chunk groups' chunks itself (trace/mcap_file.py): the
    ``mcap`` library's public ``Writer.add_message`` given the same rows' messages (one chunk open, every
    channel in it) writes the same messages, and both files load to the same arrays, bit for bit; the
    encoder's chunks each hold one chunk group's channels."""
    from mcap.writer import Writer

    from orchestrator.trace.encoding import ComponentMessages, register_mcap
    from orchestrator.trace.foxglove import FoxgloveChannels
    from orchestrator.trace.format import chunk_group

    config = paper(f"simulation.stop_time={SHORT_STOP}")
    components = [(name, [k for k in short.component(name) if k != "t"]) for name in COMPONENTS]
    rows = [(t, [[float(short.component(n)[k][i]) for k in outputs] for n, outputs in components])
            for i, t in enumerate(short.component("target")["t"].tolist())]

    def write(path: Path, chunk_size: int = 1 << 30) -> Path:
        writer = TraceWriter(path, components, every=1, foxglove=FoxgloveChannels(config, components),
                             flush_interval=1e9, chunk_size=chunk_size)
        writer.metadata("m", {"k": "v"})
        for t, outputs in rows:
            writer.record(t, outputs)
        writer.flush()  # the log line after every row (its sequence number: the rows before it)
        writer.log(SHORT_STOP, "Info", "done")
        writer.close()
        return path

    def reference(path: Path) -> Path:
        """The same rows' messages through the library's own Writer, message by message."""
        foxglove, messages = FoxgloveChannels(config, components), ComponentMessages(components, None)
        with open(path, "wb") as stream:
            writer = Writer(stream, chunk_size=1 << 30)
            writer.start(profile="", library="reference")
            channels = [register_mcap(writer, spec) for spec in messages.specs]
            foxglove.register(writer)
            writer.add_metadata("m", {"k": "v"})
            for sequence, (t, outputs) in enumerate(rows):
                stamp = int(round(t * 1e9))
                flat = [t] + [value for values in outputs for value in values]
                row = list(zip(channels, messages.encode(flat))) + list(foxglove.row(t, stamp, messages.outputs(flat)))
                for channel, data in row:
                    writer.add_message(channel_id=channel, log_time=stamp, publish_time=stamp, sequence=sequence,
                                       data=data)
            foxglove.log(lambda channel, stamp, data: writer.add_message(
                channel_id=channel, log_time=stamp, publish_time=stamp, sequence=len(rows), data=data),
                SHORT_STOP, "Info", "done")
            writer.finish()
        return path

    ours = write(tmp_path / "ours.mcap")
    write(tmp_path / "chunked.mcap", chunk_size=1 << 16)  # many chunks
    chunked = load(tmp_path / "chunked.mcap")
    assert {t: i.messages for t, i in chunked.topics.items()} == {t: i.messages for t, i in short.topics.items() if t != LOG_TOPIC} | {LOG_TOPIC: 1}
    assert chunked.component("vehicle4")["gap"].tolist() == short.component("vehicle4")["gap"].tolist()
    groups = chunk_channels(tmp_path / "chunked.mcap")
    assert len(groups) > 5
    assert all(len({chunk_group(topic) for topic in topics}) == 1 for topics in groups)  # one group a chunk
    assert {SCENE_TOPIC, TF_TOPIC} in groups and any(ERRORS_TOPIC in topics for topics in groups)
    library = reference(tmp_path / "library.mcap")
    assert len(chunk_channels(library)) == 1 and len(chunk_channels(ours)) == 3  # one chunk, or one per group
    our_messages, our_metadata = raw_messages(ours)
    library_messages, library_metadata = raw_messages(library)
    assert sorted(our_messages) == sorted(library_messages)
    assert our_metadata["m"] == library_metadata["m"]
    for topic in {topic for topic, *_ in library_messages}:  # each channel's messages in the same order
        assert [m for m in our_messages if m[0] == topic] == [m for m in library_messages if m[0] == topic]
    assert same_arrays(load(ours), load(library))
    assert load(ours).component("vehicle3")["x"].tolist() == short.component("vehicle3")["x"].tolist()


def test_the_file_layer_frames_a_file_as_the_mcap_writer_does(tmp_path: Path) -> None:
    """trace/mcap_file.py decides the records' order, the indexes and the summary as ``mcap.writer.Writer``
    does: given the Writer's compressor and the same calls (schemas, channels, metadata in the middle,
    messages filling many chunks), the two files are the same, byte for byte; the data section's CRC in DataEnd
    (which `platoon report` checks before it trusts a stored summary) is the Writer's own, with data CRCs on."""
    import io
    import random

    import zstandard
    from mcap.writer import Writer

    from orchestrator.trace.mcap_file import McapFile

    def fill(writer, finish) -> None:
        writer.start(profile="", library="either")
        schema = writer.register_schema(name="s", encoding="jsonschema", data=b"{}")
        first = writer.register_channel(topic="/a", message_encoding="json", schema_id=schema, metadata={"k": "v"})
        second = writer.register_channel(topic="/b", message_encoding="json", schema_id=0)
        writer.add_metadata("before", {"x": "1"})
        draw = random.Random(7)
        for index in range(4000):
            if index == 2000:
                writer.add_metadata("between", {"y": "2"})
                writer.register_channel(topic="/late", message_encoding="json", schema_id=schema)
            writer.add_message(channel_id=draw.choice((first, second, 3 if index > 2000 else first)),
                               log_time=index * 1000 + draw.randrange(500), publish_time=index,
                               data=b"x" * draw.randrange(1, 90), sequence=index)
        finish()

    library, ours = io.BytesIO(), io.BytesIO()
    writer = Writer(library, chunk_size=4096, enable_data_crcs=True)
    fill(writer, writer.finish)
    layer = McapFile(ours, 4096, zstandard.compress)
    fill(layer, lambda: (layer.write_open_chunk(), layer.finish()))
    assert len(library.getvalue()) > 100_000
    assert ours.getvalue() == library.getvalue()


def test_a_grouped_trace_cut_anywhere_recovers_whole_rows(tmp_path: Path, short: Trace) -> None:
    """A killed run's file ends anywhere, inside a set of chunks too: the bodies' chunk of a set is written
    after the others', so every row recovered has its errors and the channels end together."""
    config = paper(f"simulation.stop_time={SHORT_STOP}")
    components = [(name, [k for k in short.component(name) if k != "t"]) for name in COMPONENTS]
    from orchestrator.trace.foxglove import FoxgloveChannels

    path = tmp_path / "grouped.mcap"
    writer = TraceWriter(path, components, foxglove=FoxgloveChannels(config, components), flush_interval=1e9,
                         chunk_size=1 << 15)
    for i, t in enumerate(short.component("target")["t"].tolist()):
        writer.record(t, [[float(short.component(n)[k][i]) for k in outputs] for n, outputs in components])
    writer.close()
    data = path.read_bytes()
    assert len(chunk_channels(path)) > 12
    for cut in range(len(data) // 3, len(data), len(data) // 23):  # 15 or so cuts: inside chunks of every group
        (tmp_path / "cut.mcap").write_bytes(data[:cut])
        recover(tmp_path / "cut.mcap", tmp_path / "fixed.mcap")
        fixed = load(tmp_path / "fixed.mcap")
        rows = fixed.component("target")["t"]
        assert len(rows) > 10 and np.array_equal(fixed.errors["t"], rows), cut
        assert all(np.array_equal(fixed.component(name)["t"], rows) for name in COMPONENTS), cut
        assert np.array_equal(rows, short.component("target")["t"][:len(rows)])


def test_non_finite_output_ends_the_trace_before_it(tmp_path: Path) -> None:
    path = tmp_path / "nan.mcap"
    writer = TraceWriter(path, [("a", ["x"]), ("b", ["y", "z"])], block=1000)
    for k in range(5):
        writer.record(k * 0.1, [[float(k)], [1.0, math.nan if k == 3 else 2.0]])
    with pytest.raises(ComponentError, match=r"b failed at t = 0.3 s: output z = nan is not finite"):
        writer.flush()
    writer.close()
    trace = load(path)
    assert trace.component("a")["t"].tolist() == [0.0, 0.1, 0.2]
    assert trace.component("b")["z"].tolist() == [2.0, 2.0, 2.0]


def test_traces_without_channel_kinds_still_load(tmp_path: Path) -> None:
    """Files written before channels carried ``platoon.kind``: every JSON /platoon/ channel is a component."""
    from mcap.writer import CompressionType, Writer

    path = tmp_path / "old.mcap"
    with open(path, "wb") as stream:
        writer = Writer(stream, compression=CompressionType.ZSTD)
        writer.start()
        schema = writer.register_schema("platoon.target", "jsonschema", b'{"type":"object"}')
        channel = writer.register_channel("/platoon/target", "json", schema)
        for k in range(3):
            writer.add_message(channel, k * 10_000_000, json.dumps({"t": k * 0.01, "x": float(k)}).encode(), k * 10_000_000)
        writer.finish()
    trace = load(path)
    assert list(trace.channels) == ["target"] and trace.component("target")["x"].tolist() == [0.0, 1.0, 2.0]


def test_run_without_a_trace(fmu_dir: Path) -> None:
    result = run_scenario(paper("simulation.stop_time=0.5"), "", None, fmu_dir=fmu_dir)
    assert result.status == "completed" and result.trace is None and result.steps == 50


# --- an FMU that fails mid-run ------------------------------------------------------------------



@pytest.mark.parametrize("engine, writer", [("native", "inline"), ("native", "process"), ("python", "process")])
def test_fmu_failure_leaves_a_readable_trace_with_the_error_logged(tmp_path: Path, fmu_dir: Path, engine: str,
                                                                   writer: str) -> None:
    source = tmp_path / "speed_to_zero.toml"
    source.write_text(PAPER.read_text() + SPEED_TO_ZERO)
    config, _ = load_config(source, ["simulation.stop_time=2.0"])
    out = tmp_path / "failed.mcap"
    result = run_scenario(config, source.read_text(), out, engine=engine, fmu_dir=fmu_dir, trace_writer=writer)
    assert result.status == "failed"
    trace = load(out)
    assert trace.metadata["platoon.start"]["trace_writer"] == writer
    assert trace.run["status"] == "failed" and trace.run["error"].startswith("vehicle4 failed at t = 1 s")
    for name in COMPONENTS:
        t = trace.component(name)["t"]
        assert len(t) == 101 and t[-1] == pytest.approx(1.0)
    assert len(trace.errors["t"]) == 101
    last = trace.log[-1]
    assert last.level == "Error" and last.t == pytest.approx(1.0)
    assert last.message == f"run failed: {trace.run['error']}"


# --- the trace written by a second process ------------------------------------------------------

def raw_messages(path: Path) -> tuple[list[tuple[str, int, int, bytes]], dict[str, dict[str, str]]]:
    from mcap.reader import make_reader

    with open(path, "rb") as stream:
        reader = make_reader(stream, validate_crcs=True)
        messages = [(c.topic, m.log_time, m.sequence, m.data) for _, c, m in reader.iter_messages(log_time_order=False)]
        metadata = {m.name: dict(m.metadata) for m in reader.iter_metadata()}
    return messages, metadata


@pytest.mark.parametrize("engine, every", [("native", 1), ("native", 7), ("python", 3)])
def test_process_writer_writes_the_inline_file(tmp_path: Path, fmu_dir: Path, engine: str, every: int) -> None:
    """Same messages, byte for byte and in the same order; only the writer's name and start time differ."""
    config = paper("simulation.stop_time=3.0", f"simulation.trace_every={every}")
    files = {}
    for writer in ("inline", "process"):
        files[writer] = tmp_path / f"{writer}.mcap"
        result = run_scenario(config, PAPER.read_text(), files[writer], engine=engine, fmu_dir=fmu_dir, trace_writer=writer)
        assert result.status == "completed", result.error
    inline, inline_metadata = raw_messages(files["inline"])
    process, process_metadata = raw_messages(files["process"])
    assert len(inline) == len(process) > 300 // every * len(COMPONENTS)
    assert inline == process
    for metadata in (inline_metadata, process_metadata):
        metadata["platoon.start"].pop("started")
        metadata["platoon.start"].pop("trace_writer")
    assert inline_metadata == process_metadata


def test_auto_picks_a_second_process_for_long_runs_only() -> None:
    from orchestrator.execution.run import WORKER_MESSAGES, choose_trace_writer

    spare = len(os.sched_getaffinity(0)) >= 2
    assert choose_trace_writer("auto", WORKER_MESSAGES // 5, 5) == ("process" if spare else "inline")
    assert choose_trace_writer("auto", WORKER_MESSAGES // 5 - 1, 5) == "inline"
    assert choose_trace_writer("inline", 10**9, 5) == "inline"
    assert choose_trace_writer("process", 1, 5) == "process"
    with pytest.raises(ValueError, match="unknown trace writer 'threads'"):
        choose_trace_writer("threads", 1, 5)


def test_non_finite_block_ends_the_trace_before_it(tmp_path: Path) -> None:
    from orchestrator.trace.worker import TraceWorker

    rows = np.array([[k * 0.1, float(k), 1.0, 2.0] for k in range(5)])
    rows[3, 3] = math.inf
    for make in (TraceWriter, TraceWorker):
        path = tmp_path / f"{make.__name__}.mcap"
        writer = make(path, [("a", ["x"]), ("b", ["y", "z"])])
        with pytest.raises(ComponentError, match=r"b failed at t = 0.3 s: output z = inf is not finite"):
            writer.write_block(rows)
        assert writer.rows_recorded == 3 and writer.last_time == pytest.approx(0.2)
        writer.close()
        trace = load(path)
        assert trace.component("a")["x"].tolist() == [0.0, 1.0, 2.0], make.__name__


def _recoverable_steps(path: Path, probe: Path) -> int:
    """Rows that `platoon trace recover` finds in a trace being written (0 while its header is not whole)."""
    try:
        return recover(path, probe).steps
    except TraceError:
        return 0


def test_trace_writer_process_death_is_reported_and_the_chunks_stay(tmp_path: Path) -> None:
    from orchestrator.trace.worker import TraceWorker, TraceWorkerError

    path = tmp_path / "lost-writer.mcap"
    writer = TraceWorker(path, [("a", ["x"])], flush_interval=0.0)
    writer.write_block(np.array([[k * 0.1, float(k)] for k in range(100)]))
    deadline = time.monotonic() + 60
    # the worker wrote a whole chunk (the file's first bytes, its header and the channels' copies, come
    # before any: a size alone let a loaded machine kill the worker before it wrote the chunk)
    while _recoverable_steps(path, tmp_path / "probe.mcap") < 1:
        assert time.monotonic() < deadline, "the worker wrote no chunk within 60 s"
        time.sleep(0.02)
    writer._process.kill()
    writer._process.wait()
    with pytest.raises(TraceWorkerError, match="trace writer process failed.*platoon trace recover"):
        for k in range(100):  # the broken pipe shows at the next hand-over
            writer.write_block(np.array([[10.0 + k, 1.0]]))
    writer.close()  # already reported: no second error
    recovered = recover(path, tmp_path / "fixed.mcap")
    assert recovered.steps >= 1 and load(tmp_path / "fixed.mcap").component("a")["x"][0] == 0.0


def test_run_whose_trace_writer_process_dies_fails_cleanly_and_the_chunks_stay(tmp_path: Path, fmu_dir: Path) -> None:
    """The worker killed mid-run: the run ends "failed" naming the trace writer and the recover command,
    no exception escapes, and the file's complete chunks recover."""
    config = paper("simulation.stop_time=300.0")
    out = tmp_path / "worker-killed.mcap"
    aside = tmp_path / "worker-killed.mcap.partial"
    killed = []

    def tick(k: int) -> None:
        if not killed and aside.stat().st_size > 300_000:  # the worker has written chunks (aside, until finalized)
            children = Path(f"/proc/{os.getpid()}/task/{os.getpid()}/children").read_text().split()
            workers = [int(pid) for pid in children
                       if "orchestrator.trace.serve" in Path(f"/proc/{pid}/cmdline").read_bytes().decode(errors="replace")]
            assert len(workers) == 1
            os.kill(workers[0], signal.SIGKILL)
            killed.append(workers[0])

    result = run_scenario(config, PAPER.read_text(), out, fmu_dir=fmu_dir, tick=tick, trace_writer="process")
    assert killed and result.status == "failed"
    assert result.error.startswith("the trace writer process failed") and "platoon trace recover" in result.error
    assert result.trace == aside and not out.exists()  # never finalized: the data stays aside
    recovered = recover(aside, tmp_path / "fixed.mcap")
    assert recovered.steps >= 1 and not recovered.finished


def test_trace_writer_process_reports_a_bad_argument(tmp_path: Path) -> None:
    """An error inside the worker (here: a component list the writer rejects) surfaces in the caller."""
    from orchestrator.trace.worker import TraceWorker, TraceWorkerError

    writer = TraceWorker(tmp_path / "bad.mcap", [("a", ["x"])], foxglove=("not a config", [("a", ["x"])], 10.0))
    with pytest.raises(TraceWorkerError, match="AttributeError"):
        writer.metadata("m", {"k": "v"})
        writer.close()


# --- decimation through the CLI ------------------------------------------------------------------

def test_trace_every_option_and_export_command(tmp_path: Path) -> None:
    out = tmp_path / "decimated.mcap"
    result = platoon("run", PAPER, "--set", "simulation.stop_time=2.0", "--trace-every", "10", "--out", out, "-q",
                     cwd=tmp_path)
    assert result.returncode == 0, result.stderr
    trace = load(out)
    assert trace.config["simulation"]["trace_every"] == 10
    for name in COMPONENTS:
        assert np.allclose(trace.component(name)["t"], np.arange(21) * 0.1, rtol=0, atol=1e-12)
    assert len(trace.errors["t"]) == 21
    exported = platoon("export", out, "--csv", tmp_path / "csv", cwd=tmp_path)
    assert exported.returncode == 0, exported.stderr
    with open(tmp_path / "csv" / "vehicle3.csv", newline="") as stream:
        rows = list(csv.reader(stream))
    assert rows[0] == list(trace.component("vehicle3")) and len(rows) == 22
    missing = platoon("export", tmp_path / "nothing.mcap", "--csv", tmp_path / "x", cwd=tmp_path)
    assert missing.returncode == 2 and "no such file" in missing.stderr


# --- signals on a real subprocess ------------------------------------------------------------------

LONG = ("--set", "simulation.stop_time=10000")


def start_long_run(trace: Path, cwd: Path, writer: str) -> subprocess.Popen[str]:
    """`platoon run` of a 10000 s scenario in its own process group (as a shell job is), with the trace
    encoded by ``writer`` ("inline" or "process"); returns once its trace holds a MB of chunks (~1500
    steps: an event, not a guess at how long that takes). Not much more: the tests read back every step
    the run wrote, ~0.15 ms of CPU each (2 s of a native run are ~90 000 steps, 13 s of reading)."""
    process = subprocess.Popen(
        [str(PLATOON), "run", str(PAPER), *LONG, "--out", str(trace), "-q", "--trace-writer", writer], cwd=cwd,
        env=env(), stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, start_new_session=True,
        # a test runner started in the background may hand down SIGINT ignored; a user's shell does not
        preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL),
    )
    started = time.monotonic()
    while time.monotonic() - started < 60:
        if process.poll() is not None:
            raise AssertionError(f"run ended early ({process.returncode}): {process.stderr.read()}")
        aside = trace.with_name(trace.name + ".partial")  # where a run writes until it finalizes the trace
        if aside.is_file() and aside.stat().st_size > 1_000_000:
            return process
        time.sleep(0.05)
    os.killpg(process.pid, signal.SIGKILL)
    raise AssertionError("the trace did not grow within 60 s")


def group_members(process: subprocess.Popen[str]) -> list[int]:
    """Process ids in the run's process group (the run and its trace writer, if any)."""
    members = []
    for entry in Path("/proc").iterdir():
        if entry.name.isdigit():
            try:
                if os.getpgid(int(entry.name)) == process.pid:
                    members.append(int(entry.name))
            except ProcessLookupError:
                pass
    return members


def wait_group_gone(process: subprocess.Popen[str], timeout: float = 60) -> None:
    deadline = time.monotonic() + timeout
    while group_members(process) and time.monotonic() < deadline:
        time.sleep(0.05)
    assert not group_members(process), "a process of the run outlived it"


def assert_consistent(trace: Trace, step: float = 0.01) -> float:
    """Every component and the errors end at the same time, on the grid, with no gap; returns it."""
    reference = trace.component("target")["t"]
    assert len(reference) > 10 and reference[-1] > 0
    assert np.allclose(np.diff(reference), step, rtol=0, atol=1e-9)  # increasing, no gaps
    for name in COMPONENTS:
        assert np.array_equal(trace.component(name)["t"], reference), name
        assert np.array_equal(trace.component(name)["output_time"], reference), name
    assert np.array_equal(trace.errors["t"], reference)
    return float(reference[-1])


# (signal, sent to the whole process group as a terminal's Ctrl-C is, trace writer)
SIGNAL_CASES = {
    "SIGINT-group-process": (signal.SIGINT, True, "process"),
    "SIGTERM-process": (signal.SIGTERM, False, "process"),
    "SIGINT-inline": (signal.SIGINT, False, "inline"),
}


@pytest.fixture(scope="module")
def signalled(tmp_path_factory: pytest.TempPathFactory):
    """Signalled runs: {case: (exit code, stderr, trace path)}."""
    folder = tmp_path_factory.mktemp("signals")
    results = {}
    for case, (signum, group, writer) in SIGNAL_CASES.items():
        trace = folder / f"{case}.mcap"
        process = start_long_run(trace, folder, writer)
        try:
            if group:
                os.killpg(process.pid, signum)
            else:
                process.send_signal(signum)
            stdout, stderr = process.communicate(timeout=60)
            wait_group_gone(process)  # the trace writer finished too
        except BaseException:
            os.killpg(process.pid, signal.SIGKILL)
            raise
        results[case] = (process.returncode, stderr, trace)
    return results


@pytest.mark.parametrize("case", list(SIGNAL_CASES))
def test_signal_finalizes_the_trace(signalled, case: str) -> None:
    signum, _, writer = SIGNAL_CASES[case]
    code, stderr, path = signalled[case]
    assert code == 128 + signum, stderr  # 130 for SIGINT, 143 for SIGTERM
    assert "Traceback" not in stderr
    assert stderr.startswith("error: run interrupted: ") and str(path) in stderr, stderr
    trace = load(path)  # finalized: footer, summary, indexes
    last = assert_consistent(trace)
    assert trace.metadata["platoon.start"]["trace_writer"] == writer
    assert trace.run["status"] == "interrupted"
    assert trace.run["signal"] == signal.Signals(signum).name
    assert float(trace.run["last_time"]) == last
    assert trace.run["steps_recorded"] == str(len(trace.component("target")["t"]))
    assert f"at t = {last:.6g} s" in trace.run["error"]
    assert trace.log[-1].level == "Warning" and signal.Signals(signum).name in trace.log[-1].message
    assert trace.topics[SCENE_TOPIC].messages == int(last * 10 + 1e-6) + 1


@pytest.fixture(scope="module", params=["process", "inline"])
def killed(request, tmp_path_factory: pytest.TempPathFactory):
    """A run whose whole process group was killed with SIGKILL: (broken path, CLI result, recovered path, Recovery)."""
    folder = tmp_path_factory.mktemp(f"killed-{request.param}")
    trace = folder / "killed.mcap"
    process = start_long_run(trace, folder, request.param)
    try:
        assert len(group_members(process)) == (2 if request.param == "process" else 1)  # the run (and its writer)
    finally:
        os.killpg(process.pid, signal.SIGKILL)  # never leave a 10000 s run behind
    process.communicate(timeout=60)
    assert process.returncode == -signal.SIGKILL
    wait_group_gone(process)
    broken = trace.with_name(trace.name + ".partial")  # never finalized: the data stays in the aside file
    assert not trace.exists()
    fixed = folder / "fixed.mcap"
    cli = platoon("trace", "recover", broken, "--out", fixed, cwd=folder)
    details = recover(broken, folder / "fixed-again.mcap")
    return broken, cli, fixed, details


def test_killed_trace_is_unfinished_and_says_how_to_recover(killed) -> None:
    broken = killed[0]
    with pytest.raises(TraceError, match="platoon trace recover"):
        load(broken)


def written_chunk_groups(path: Path) -> list[set[int]]:
    """The chunk groups of each complete chunk of a trace read in file order (a killed run's too)."""
    from mcap.exceptions import EndOfFile
    from mcap.records import Channel, Chunk, Message
    from mcap.stream_reader import StreamReader, breakup_chunk
    from orchestrator.trace.format import chunk_group

    topics: dict[int, str] = {}
    groups = []
    with open(path, "rb") as stream:
        try:
            for record in StreamReader(stream, emit_chunks=True).records:
                if isinstance(record, Chunk):
                    items = breakup_chunk(record)
                    topics.update({item.id: item.topic for item in items if isinstance(item, Channel)})
                    groups.append({chunk_group(topics[item.channel_id]) for item in items if isinstance(item, Message)})
        except EndOfFile:  # a killed run's file ends inside a record
            pass
    return groups


def test_recover_after_sigkill(killed) -> None:
    broken, cli, fixed, details = killed
    assert cli.returncode == 0, cli.stderr
    groups = written_chunk_groups(broken)  # the killed file's chunks each hold one chunk group
    assert all(len(group) == 1 for group in groups) and len(set().union(*groups)) == 3
    assert f"recovered {details.steps} communication points" in cli.stdout and str(fixed) in cli.stdout
    assert not details.finished and details.chunks >= 1
    trace = load(fixed)
    last = assert_consistent(trace)
    assert details.steps == len(trace.component("target")["t"]) and details.last_time == pytest.approx(last)
    # at most the part of one row that a chunk boundary cut is dropped (5 components + errors channel), or,
    # when the run was killed while it wrote a set of chunks (one per chunk group, the bodies' last), the
    # other groups' messages of that set: fewer than a set's share of the messages
    assert details.dropped < len(COMPONENTS) + 1 + 3 or details.dropped < 3 * details.messages / details.chunks
    assert trace.run["status"] == "recovered" and trace.run["engine"] in ("native", "python")
    assert trace.run["steps_recorded"] == str(details.steps)
    assert trace.config["simulation"]["stop_time"] == 10000.0
    assert trace.topics[SCENE_TOPIC].messages >= int(last * 10) - 1  # scenes survive up to the end too
    assert trace.log[0].message.startswith("run started")


def test_orphaned_trace_writer_finalizes_what_it_received(tmp_path: Path) -> None:
    """SIGKILL of the stepping process alone: its trace writer process keeps and finalizes every point."""
    path = tmp_path / "orphaned.mcap"
    process = start_long_run(path, tmp_path, "process")
    process.send_signal(signal.SIGKILL)
    process.communicate(timeout=60)
    try:
        wait_group_gone(process)
    finally:
        if group_members(process):
            os.killpg(process.pid, signal.SIGKILL)
    trace = load(path)  # finalized by the worker: no recovery needed
    last = assert_consistent(trace)
    assert last > 1.0
    assert trace.run["status"] == "aborted" and "killed?" in trace.run["error"]
    assert trace.run["steps_recorded"] == str(len(trace.component("target")["t"]))
    assert trace.log[-1].level == "Error" and trace.log[-1].message.startswith("run aborted")
    assert trace.topics[SCENE_TOPIC].messages == int(last * 10 + 1e-6) + 1


def test_recover_cli_bad_input(tmp_path: Path) -> None:
    bogus = tmp_path / "bogus.mcap"
    bogus.write_text("not an MCAP file at all\n")
    result = platoon("trace", "recover", bogus, cwd=tmp_path)
    assert result.returncode == 2 and "not an MCAP file" in result.stderr, result.stderr
    missing = platoon("trace", "recover", tmp_path / "none.mcap", cwd=tmp_path)
    assert missing.returncode == 2 and "no such file" in missing.stderr


# --- an independent reader: @mcap/core (TypeScript) under Node --------------------------------------

@pytest.fixture(scope="module")
def mcap_js() -> Path:
    node, npm = shutil.which("node"), shutil.which("npm")
    if node is None or npm is None:
        pytest.skip("node/npm not installed: the independent @mcap/core reader cannot run")
    # Parallel workers share tests/mcap_js: one installs under the lock while the others wait (two
    # concurrent `npm ci` runs delete each other's node_modules). The install counts as done only when
    # every package the reader imports is there; npm writes its hidden lockfile last.
    with open(MCAP_JS / ".install.lock", "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        _npm_install(npm)
    return MCAP_JS / "read_mcap.mjs"


def _npm_install(npm: str) -> None:
    modules = MCAP_JS / "node_modules"
    wanted = json.loads((MCAP_JS / "package.json").read_text())["dependencies"]
    if (modules / ".package-lock.json").is_file() and all((modules / name).is_dir() for name in wanted):
        return
    try:
        done = subprocess.run([npm, "ci", "--no-audit", "--no-fund"], cwd=MCAP_JS, capture_output=True, text=True,
                              timeout=300)
    except subprocess.TimeoutExpired:
        pytest.skip("npm ci timed out: the npm registry is not reachable")
    if done.returncode != 0:
        text = done.stderr + done.stdout
        if any(s in text for s in ("ENOTFOUND", "ECONNREFUSED", "ETIMEDOUT", "EAI_AGAIN", "network", "ECONNRESET")):
            pytest.skip(f"npm cannot reach the registry: {text.strip().splitlines()[-1]}")
        raise AssertionError(f"npm ci failed:\n{text}")


def read_js(script: Path, path: Path) -> dict:
    done = subprocess.run(["node", str(script), str(path)], capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr
    return json.loads(done.stdout)


def _flatten(record: dict, prefix: str = "") -> dict:
    flat = {}
    for key, value in record.items():
        flat.update(_flatten(value, f"{prefix}{key}.") if isinstance(value, dict) else {prefix + key: value})
    return flat


def test_independent_reader_sees_the_same_trace(mcap_js: Path, short: Trace) -> None:
    js = read_js(mcap_js, short.path)
    stream, indexed = js["stream"], js["indexed"]
    assert stream["done"] and stream["records"]["Footer"] == 1
    counts = {topic: info.messages for topic, info in short.topics.items()}
    assert stream["counts"] == counts  # every record in file order, CRCs checked
    assert {t: i["count"] for t, i in indexed["topics"].items()} == counts  # through the indexes
    assert {t: int(n) for t, n in indexed["statistics"]["channelMessageCounts"].items()} == counts
    for topic, info in short.topics.items():
        assert indexed["topics"][topic]["schema"] == info.schema
        assert indexed["topics"][topic]["messageEncoding"] == info.message_encoding
    assert indexed["metadata"] == short.metadata
    assert indexed["chunks"] >= 1 and indexed["library"] == "platoon-cosim"
    for name in COMPONENTS:
        messages = indexed["json"][f"/platoon/{name}"]
        columns = short.component(name)
        assert [int(m[0]) for m in messages] == [int(round(t * 1e9)) for t in columns["t"]]  # log_time = t in ns
        assert [m[0] for m in messages] == [m[1] for m in messages]  # publish_time too
        for key, column in columns.items():
            assert np.array_equal(np.array([m[3][key] for m in messages], dtype=float), column), (name, key)
    errors = [_flatten(m[3]) for m in indexed["json"][ERRORS_TOPIC]]
    for key, column in short.errors.items():
        assert np.array_equal(np.array([e[key] for e in errors], dtype=float), column), key


def test_independent_reader_on_interrupted_and_recovered_traces(mcap_js: Path, signalled, killed) -> None:
    _, _, interrupted = signalled["SIGTERM-process"]
    broken, _, fixed, details = killed
    for path in (interrupted, fixed):
        js = read_js(mcap_js, path)
        ours = load(path)
        assert js["stream"]["done"]
        assert js["stream"]["counts"] == {t: i.messages for t, i in ours.topics.items()}
        assert {t: i["count"] for t, i in js["indexed"]["topics"].items()} == js["stream"]["counts"]
        target = js["indexed"]["json"]["/platoon/target"]
        assert np.array_equal(np.array([m[3]["x"] for m in target]), ours.component("target")["x"])
    # the unfinished file itself: the independent stream reader finds the same complete chunks
    js = read_js(mcap_js, broken)
    assert not js["stream"]["done"]
    assert sum(js["stream"]["counts"].values()) == details.messages + details.dropped
