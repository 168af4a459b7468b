"""``platoon run --live``: a real WebSocket client on 127.0.0.1 watches a real run (docs/foxglove.md).

The client speaks the Foxglove WebSocket protocol as Foxglove and Lichtblick do (``websockets``, the
reference asyncio implementation): it reads the server's channel advertisements, subscribes to every
channel and decodes the binary message frames (opcode 1, subscription id, timestamp, payload). What
it receives is compared with the trace the same run wrote, read back with the ``mcap`` reader.
Nothing here depends on how fast the machine is: the client waits for events (connection, messages,
the server closing at the end of the run), never for a duration.
"""

from __future__ import annotations

import asyncio
import base64
import json
import os
import signal
import socket
import struct
import subprocess
import sys
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pytest

from orchestrator.trace import load

websockets = pytest.importorskip("websockets")

REPO = Path(__file__).resolve().parents[1]
PLATOON = Path(sys.executable).parent / "platoon"
PAPER = REPO / "configs" / "paper" / "platoon.toml"
VEHICLES = ["vehicle1", "vehicle2", "vehicle3", "vehicle4"]
GIVE_UP = 120.0  # s: only a guard against a hung run, never a measurement

from tests.conftest import free_port


def start_run(out: Path, port: int, *args: str, config: Path = PAPER) -> subprocess.Popen[str]:
    """``platoon run --live`` as a user starts it (this tree's code), output to files beside the trace."""
    env = {**os.environ, "COLUMNS": "80", "NO_COLOR": "1", "TERM": "dumb", "PYTHONPATH": str(REPO)}
    return subprocess.Popen(
        [str(PLATOON), "run", str(config), "--out", str(out), "--live", "--live-port", str(port), *args],
        cwd=out.parent, env=env, stdout=open(out.with_suffix(".stdout"), "w"), stderr=open(out.with_suffix(".stderr"), "w"),
        text=True, preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))  # as a shell gives it, even
        # when the suite runs in the background (SIGINT handed down ignored, and the run keeps what it is given)


@dataclass
class Watched:
    """What the client saw: the advertised channels by id, every message (topic, timestamp, payload) and
    the server's time announcements (ns)."""

    channels: dict[int, dict] = field(default_factory=dict)
    advertised_first: list[dict] = field(default_factory=list)  # the channels of the server's first advertisement
    messages: list[tuple[str, int, bytes]] = field(default_factory=list)
    times: list[int] = field(default_factory=list)
    closed: bool = False


CURRENT = ["foxglove.sdk.v1", "foxglove.websocket.v1"]  # as Foxglove offers them
LEGACY = ["foxglove.websocket.v1"]  # as Lichtblick 1.10.8 does (the viewer of ../shared/viewer)


async def _watch(port: int, run: subprocess.Popen[str], interrupt_after: int | None, offer: list[str]) -> Watched:
    url = f"ws://127.0.0.1:{port}"
    seen = Watched()
    while True:  # the port opens once the config is read; the handshake completes once the channels exist
        try:
            connection = await websockets.connect(url, subprotocols=offer, open_timeout=None)
            break
        except OSError:
            if run.poll() is not None:
                raise AssertionError(f"the run ended (exit {run.returncode}) before its live view accepted a client")
            await asyncio.sleep(0.05)
    async with connection:
        assert connection.subprotocol == offer[0]
        frames = 0
        while True:
            try:
                data = await connection.recv()
            except websockets.ConnectionClosed:
                seen.closed = True
                return seen
            if isinstance(data, str):
                message = json.loads(data)
                if message["op"] == "advertise":
                    if not seen.channels:
                        seen.advertised_first = list(message["channels"])
                    for channel in message["channels"]:
                        seen.channels[channel["id"]] = channel
                    await connection.send(json.dumps({"op": "subscribe", "subscriptions": [
                        {"id": channel["id"], "channelId": channel["id"]} for channel in message["channels"]]}))
                continue
            if data[0] == 2:  # Time: the server's clock, the simulated time of the frame that follows
                seen.times.append(struct.unpack_from("<Q", data, 1)[0])
                continue
            assert data[0] == 1  # MessageData
            subscription, stamp = struct.unpack_from("<IQ", data, 1)
            topic = seen.channels[subscription]["topic"]
            seen.messages.append((topic, stamp, bytes(data[13:])))
            if topic == "/platoon/scene":
                frames += 1
                if interrupt_after is not None and frames == interrupt_after:
                    run.send_signal(signal.SIGINT)  # as Ctrl-C in the terminal


def watch(port: int, run: subprocess.Popen[str], interrupt_after: int | None = None, offer: list[str] = CURRENT) -> Watched:
    try:
        seen = asyncio.run(asyncio.wait_for(_watch(port, run, interrupt_after, offer), GIVE_UP))
        run.wait(timeout=GIVE_UP)
    finally:
        if run.poll() is None:
            run.kill()
    return seen


def trace_channels(path: Path) -> dict[str, tuple[str, str, str, bytes]]:
    """Topic -> (message encoding, schema name, schema encoding, schema bytes) of a trace file."""
    from mcap.reader import make_reader

    with open(path, "rb") as stream:
        summary = make_reader(stream).get_summary()
    return {c.topic: (c.message_encoding, summary.schemas[c.schema_id].name, summary.schemas[c.schema_id].encoding,
                      summary.schemas[c.schema_id].data) for c in summary.channels.values()}


def trace_messages(path: Path, topic: str) -> dict[int, bytes]:
    """Log time -> message bytes of one topic of a trace file."""
    from mcap.reader import make_reader

    with open(path, "rb") as stream:
        return {message.log_time: message.data for _, _, message in make_reader(stream).iter_messages(topics=[topic])}


def protobuf_class(channel: dict):
    """The message class of an advertised protobuf channel, from the schema the server sent (as the viewer does)."""
    pytest.importorskip("google.protobuf")
    from google.protobuf import descriptor_pb2, descriptor_pool, message_factory

    pool = descriptor_pool.DescriptorPool()
    for file in descriptor_pb2.FileDescriptorSet.FromString(base64.b64decode(channel["schema"])).file:
        pool.Add(file)
    return message_factory.GetMessageClass(pool.FindMessageTypeByName(channel["schemaName"]))


def test_foxglove_view_serves_the_traces_channels_and_data(tmp_path: Path) -> None:
    out, port = tmp_path / "live.mcap", free_port()
    run = start_run(out, port, "--set", "simulation.stop_time=4", "--live-wait")
    seen = watch(port, run)
    assert run.returncode == 0, out.with_suffix(".stderr").read_text()
    assert seen.closed  # the server closes once the run is over
    stdout = out.with_suffix(".stdout").read_text()
    assert f"ws://127.0.0.1:{port}" in stdout
    assert f"?ds=foxglove-websocket&ds.url=ws://127.0.0.1:{port}" in stdout

    # the same channels as the trace: topics, encodings, schema names and schemas
    recorded = trace_channels(out)
    advertised = {c["topic"]: c for c in seen.channels.values()}
    assert set(advertised) == set(recorded)
    for topic, (encoding, schema_name, schema_encoding, schema) in recorded.items():
        channel = advertised[topic]
        assert (channel["encoding"], channel["schemaName"], channel.get("schemaEncoding")) == (encoding, schema_name, schema_encoding)
        sent = base64.b64decode(channel["schema"]) if schema_encoding == "protobuf" else channel["schema"].encode()
        assert sent == schema, topic

    # the trace is complete: every step of the 4 s run
    trace = load(out)
    assert trace.run["status"] == "completed"
    assert len(trace.component("vehicle1")["t"]) == 401
    rows = {name: {int(round(t * 1e9)): i for i, t in enumerate(trace.component(name)["t"])} for name in ["target", *VEHICLES]}

    # every component message is the trace's values at the same simulated time (the same float text: exact)
    received = {}
    for topic, stamp, payload in seen.messages:
        name = topic.removeprefix("/platoon/")
        if name in rows:
            values = json.loads(payload)
            index = rows[name][stamp]
            assert values["t"] * 1e9 == pytest.approx(stamp, abs=1)
            for key, value in values.items():
                assert value == trace.component(name)[key][index], (topic, key, stamp)
            received[name] = received.get(name, 0) + 1
        elif topic == "/platoon/errors":
            values = json.loads(payload)
            index = rows["vehicle1"][stamp]
            for vehicle in VEHICLES:
                for key, value in values[vehicle].items():
                    assert value == trace.errors[f"{vehicle}.{key}"][index]
    assert set(received) == set(rows)

    # the scene puts each vehicle where the trace has it at that time, and ends the run's last point
    scene = protobuf_class(advertised["/platoon/scene"])
    scenes = [(stamp, scene.FromString(payload)) for topic, stamp, payload in seen.messages if topic == "/platoon/scene"]
    assert scenes
    for stamp, message in scenes:
        entities = {entity.id: entity for entity in message.entities}
        assert {"path", "target", *VEHICLES} <= set(entities)
        for name in VEHICLES:
            position = entities[name].cubes[0].pose.position
            index = rows[name][stamp]
            assert (position.x, position.y) == (trace.component(name)["x"][index], trace.component(name)["y"][index])
    assert scenes[-1][0] == int(round(4.0 * 1e9))  # the last point is shown
    # at the trace's scene ticks (10 Hz of simulated time) the frame is the trace's scene, trails included
    recorded_scenes = trace_messages(out, "/platoon/scene")
    matched = [(stamp, payload) for topic, stamp, payload in seen.messages
               if topic == "/platoon/scene" and stamp in recorded_scenes]
    assert matched and matched[-1][0] == scenes[-1][0]
    for stamp, payload in matched:
        assert payload == recorded_scenes[stamp], stamp
    # --live-wait: the run started once the client subscribed, so it saw the run from its start
    assert scenes[0][0] < 0.1e9
    assert any(b"run started" in payload for topic, _, payload in seen.messages if topic == "/platoon/log")
    stamps = [stamp for stamp, _ in scenes]
    assert stamps == sorted(stamps)
    # the viewer's clock is simulated time: the server announces each frame's time (Time capability)
    assert seen.times == sorted(seen.times) and set(stamps) <= set(seen.times)


def test_ctrl_c_during_a_live_run_keeps_a_finalized_trace(tmp_path: Path) -> None:
    """Also: a viewer that offers only the protocol's old name (Lichtblick 1.10.8) is served."""
    out, port = tmp_path / "stopped.mcap", free_port()
    run = start_run(out, port, "--set", "simulation.stop_time=60", "--engine", "python")
    seen = watch(port, run, interrupt_after=3, offer=LEGACY)
    assert run.returncode == 130, out.with_suffix(".stderr").read_text()
    trace = load(out)
    assert trace.run["status"] == "interrupted"
    last = float(trace.run["last_time"])
    assert 0.0 < last < 60.0
    t = trace.component("vehicle2")["t"]
    assert t[-1] == last and np.allclose(np.diff(t), 0.01)  # every step up to the stop
    log = [m for topic, _, m in seen.messages if topic == "/platoon/log"]
    assert log and b"interrupted by SIGINT" in log[-1]  # the viewer is told, as the trace's log says


@pytest.mark.realtime
def test_a_live_robots_run_shows_its_link_streams(tmp_path: Path) -> None:
    """A hardware-in-the-loop run (configs/hil/, the emulator standing in for robot 3): the view serves
    the robot link's raw streams as the trace records them, and the run is not paced twice."""
    from tests.test_hil import emulator, endpoint

    robot_port, port, out = free_port(), free_port(), tmp_path / "hil.mcap"
    with emulator(robot_port, tmp_path):
        run = start_run(out, port, "--set", "simulation.stop_time=2", "--set", f'vehicles.3.connect=["{endpoint(robot_port)}"]',
                        "--live-wait", config=REPO / "configs" / "hil" / "m3pi_live3.toml")
        seen = watch(port, run)
    assert run.returncode == 0, out.with_suffix(".stderr").read_text()
    assert load(out).run["status"] == "completed"
    from mcap.reader import make_reader

    streams = ("/platoon/vehicle3/pose", "/platoon/vehicle3/command", "/platoon/vehicle3/link")
    # the robot's streams are advertised with the run's other channels, before the viewer got in (a channel
    # advertised mid-run is one the SDK's server may refuse a connected viewer's subscription to)
    assert set(streams) <= {channel["topic"] for channel in seen.advertised_first}
    channels = trace_channels(out)
    for channel in seen.channels.values():
        if channel["topic"] in streams:  # the same schema as the trace's, though declared before any message
            encoding, name, schema_encoding, schema = channels[channel["topic"]]
            assert (channel["encoding"], channel["schemaName"], channel.get("schemaEncoding")) == (encoding, name, schema_encoding)
            assert channel["schema"].encode() == schema
    for topic in streams:
        received = [(stamp, payload) for t, stamp, payload in seen.messages if t == topic]
        with open(out, "rb") as stream:
            recorded = [(m.log_time, m.data) for _, _, m in make_reader(stream).iter_messages(topics=[topic], log_time_order=False)]
        # a viewer there from the start (--live-wait) has every message of the robot's link, the same bytes
        # in the same order as the trace
        assert recorded and received == recorded, topic


async def _connect_and_vanish(port: int, run: subprocess.Popen[str]) -> None:
    """A viewer that takes the first message and disappears without a closing handshake (its TCP connection
    reset, as when a laptop sleeps or a browser is killed)."""
    while True:
        try:
            connection = await websockets.connect(f"ws://127.0.0.1:{port}", subprotocols=CURRENT, open_timeout=None)
            break
        except OSError:
            assert run.poll() is None, "the run ended before its live view accepted a client"
            await asyncio.sleep(0.05)
    await connection.recv()
    raw = connection.transport.get_extra_info("socket")
    raw.setsockopt(socket.SOL_SOCKET, socket.SO_LINGER, struct.pack("ii", 1, 0))  # close -> RST, no FIN
    connection.transport.abort()


def test_a_viewer_that_vanishes_is_not_reported_as_an_error(tmp_path: Path) -> None:
    port = free_port()
    out = tmp_path / "vanish.mcap"
    run = start_run(out, port, "--set", "simulation.stop_time=2")
    try:
        asyncio.run(asyncio.wait_for(_connect_and_vanish(port, run), GIVE_UP))
        run.wait(timeout=GIVE_UP)
    finally:
        if run.poll() is None:
            run.kill()
    stderr = out.with_suffix(".stderr").read_text()
    assert run.returncode == 0, stderr
    assert "Connection reset" not in stderr and "Error receiving" not in stderr, stderr  # the SDK's raw line is gone
    assert load(out).run["status"] == "completed"


def test_a_port_in_use_exits_2_with_one_line_and_writes_nothing(tmp_path: Path) -> None:
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        port = taken.getsockname()[1]
        out = tmp_path / "busy.mcap"
        run = start_run(out, port)
        run.wait(timeout=GIVE_UP)
    assert run.returncode == 2
    stderr = out.with_suffix(".stderr").read_text()
    lines = stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: ") and f"127.0.0.1:{port}" in lines[0], stderr
    assert "Traceback" not in stderr
    assert sorted(p.name for p in tmp_path.iterdir()) == ["busy.stderr", "busy.stdout"]  # no trace, aside file or layout


def test_live_options_are_checked_before_anything_is_written(tmp_path: Path) -> None:
    out = tmp_path / "hil.mcap"
    env = {**os.environ, "COLUMNS": "200", "NO_COLOR": "1", "TERM": "dumb", "PYTHONPATH": str(REPO)}
    result = subprocess.run([str(PLATOON), "run", str(REPO / "configs" / "hil" / "m3pi_live3.toml"), "--out", str(out),
                             "--live", "--live-port", str(free_port()), "--live-speed", "5"],
                            cwd=tmp_path, env=env, capture_output=True, text=True, timeout=GIVE_UP)
    assert result.returncode == 2
    assert result.stderr.startswith("error: --live-speed 5: ") and "live robot" in result.stderr
    assert list(tmp_path.iterdir()) == []


def test_the_steps_time_leaves_out_the_wait_for_a_viewer(tmp_path: Path) -> None:
    """--live-wait: "N steps in X s" counts the run's own work, not the seconds it waited for a viewer.
    The viewer comes HOLD s after the run says it waits (a wait made on purpose: it is what is measured);
    the run itself, 200 steps at --live-speed 0 (as fast as it runs), takes a fraction of a second, so X
    stays under HOLD / 2 on a loaded machine, and would exceed it if the wait were counted."""
    import re
    import time

    hold = 5.0
    out, port = tmp_path / "waited.mcap", free_port()
    run = start_run(out, port, "--set", "simulation.stop_time=2", "--live-wait", "--live-speed", "0")
    stdout = out.with_suffix(".stdout")
    deadline = time.monotonic() + GIVE_UP
    while "waiting for a viewer" not in stdout.read_text():  # the run's announcement (rich flushes each line)
        assert run.poll() is None and time.monotonic() < deadline, out.with_suffix(".stderr").read_text()
        time.sleep(0.05)
    time.sleep(hold)
    watch(port, run)
    assert run.returncode == 0, out.with_suffix(".stderr").read_text()
    done = re.search(r"\((\d+) steps in ([\d.]+) s\)", stdout.read_text())
    assert done and int(done.group(1)) == 200, stdout.read_text()
    assert float(done.group(2)) < hold / 2, stdout.read_text()
