"""Hardware in the loop over Zenoh, end to end: real processes, real Zenoh sessions on 127.0.0.1.

The m3pi emulator (``platoon m3pi-emulator``) runs as its own process and stands in for robot 3 of
configs/hil/m3pi_live3.toml; ``platoon run`` steers it. Faults are made for real: the emulator is
killed (SIGKILL) or frozen (SIGSTOP), garbage is published on the robot's pose key from a third
Zenoh session, the run gets SIGINT. Unit tests of the protocol, the emulator's watchdog and the pacer
use no network.
"""

from __future__ import annotations

import math
import os
import signal
import subprocess
import sys
import time
from contextlib import contextmanager
from pathlib import Path
from typing import Callable, Iterator

import numpy as np
import pytest
import zenoh

from bridge.protocol import (
    MAX_PAYLOAD,
    Drop,
    MessageError,
    Pose,
    RobotKeys,
    SequenceCheck,
    WheelCommand,
    check_pose_time,
    decode_pose,
    decode_wheels,
    encode_pose,
    encode_wheels,
)
from orchestrator.bench.hil import free_port
from orchestrator.scenario.config import config_from_mapping
from orchestrator.analysis.metrics import path_errors
from fmus.realtime import Pacer
from orchestrator.trace import load

REPO = Path(__file__).resolve().parents[1]
PLATOON = Path(sys.executable).parent / "platoon"
LIVE3 = REPO / "configs" / "hil" / "m3pi_live3.toml"
KEYS = RobotKeys("platoon", 3)


# -- protocol, no network ------------------------------------------------------------------------

def test_pose_and_wheel_messages_round_trip_exactly() -> None:
    pose = Pose(7, 5, 1.7e9 + 0.125, -0.25, 1.0 / 3.0, -3.1)
    assert decode_pose(encode_pose(pose)) == pose
    command = WheelCommand(9, 1.7e9 + 0.1, -0.2, 0.35)
    assert decode_wheels(encode_wheels(command)) == command
    assert len(encode_pose(pose)) == 44 and len(encode_wheels(command)) == 32


@pytest.mark.parametrize("payload, reason, text", [
    (bytes(MAX_PAYLOAD + 1), Drop.OVERSIZED, "257 bytes, more than 256"),
    (b"", Drop.MALFORMED, "0 bytes, expected 44"),
    (encode_pose(Pose(1, 0, 1.0, 0.0, 0.0, 0.0))[:-1], Drop.MALFORMED, "43 bytes, expected 44"),
    (b"\x02" + encode_pose(Pose(1, 0, 1.0, 0.0, 0.0, 0.0))[1:], Drop.VERSION, "protocol version 2, expected 1"),
    (encode_wheels(WheelCommand(1, 1.0, 0.0, 0.0)) + bytes(12), Drop.MALFORMED, "message kind 2, expected 1"),
    (encode_pose(Pose(1, 0, 1.0, math.nan, 0.0, math.inf)), Drop.NON_FINITE, "x = nan, heading = inf (not finite)"),
])
def test_a_bad_pose_is_refused_with_its_reason(payload: bytes, reason: Drop, text: str) -> None:
    with pytest.raises(MessageError) as refused:
        decode_pose(payload)
    assert refused.value.reason is reason
    assert text in str(refused.value)


def test_sequence_and_age_checks_name_the_problem() -> None:
    check = SequenceCheck()
    check.check(1, "pose 1")
    check.check(3, "pose 3")
    with pytest.raises(MessageError, match="sequence number 3 again") as duplicate:
        check.check(3, "pose 3")
    assert duplicate.value.reason is Drop.DUPLICATE
    with pytest.raises(MessageError, match="sequence number 2 after 3") as older:
        check.check(2, "pose 2")
    assert older.value.reason is Drop.OUT_OF_ORDER
    pose = Pose(4, 0, 100.0, 0.0, 0.0, 0.0)
    check_pose_time(pose, 100.2, max_age=0.25)
    with pytest.raises(MessageError, match="300.0 ms old") as late:
        check_pose_time(pose, 100.3, max_age=0.25)
    assert late.value.reason is Drop.LATE
    with pytest.raises(MessageError, match="ahead of this clock") as ahead:
        check_pose_time(pose, 99.0, max_age=0.25)
    assert ahead.value.reason is Drop.FUTURE


# -- emulator physics and watchdog, no network -----------------------------------------------------

def _robot(command_latency: float = 0.0, flying_start: bool = True):
    from bridge.emulator import EmulatedRobot, EmulatorSettings, RobotSpec
    from fmus.model.dynamics import M3piDynamics

    said: list[str] = []
    spec = RobotSpec(KEYS, 0.0, 0.0, 0.0, 0.3, M3piDynamics(0.5))
    settings = EmulatorSettings(command_latency=command_latency, command_timeout=0.25, flying_start=flying_start)
    robot = EmulatedRobot(spec, settings, said.append)
    robot.time = 100.0
    return robot, said


def test_emulated_robot_stands_until_commanded_then_drives_and_stops_at_the_deadline() -> None:
    robot, said = _robot()
    robot.advance(101.0)
    assert robot.state[:3] == [0.0, 0.0, 0.0]  # no command yet: it stands on its mark
    robot.receive(encode_wheels(WheelCommand(1, 101.1, 0.3, 0.3)), 101.0)
    assert robot.state[3:] == [0.3, 0.3]  # flying start: rolling at the config's initial speed
    robot.advance(101.1)
    assert robot.state[0] == pytest.approx(0.03, abs=1e-12)  # 0.1 s at 0.3 m/s, straight ahead
    robot.advance(101.6)  # the deadline passed at 101.1: wheels commanded to zero, the motors run down
    assert robot.command == (0.0, 0.0)
    assert abs(robot.state[3]) < 0.3 * math.exp(-0.5 / 0.05) * 1.01
    assert "running -> stopped (command deadline passed)" in said[-1]


def test_emulated_robot_applies_a_command_after_the_radio_latency_and_refuses_late_ones() -> None:
    robot, said = _robot(command_latency=0.02, flying_start=False)
    robot.receive(encode_wheels(WheelCommand(1, 100.5, 0.2, 0.4)), 100.0)
    robot.advance(100.019)
    assert robot.command == (0.0, 0.0)
    robot.advance(100.021)
    assert robot.command == (0.2, 0.4) and robot.command_seq == 1
    robot.receive(encode_wheels(WheelCommand(2, 100.0, 0.1, 0.1)), 100.03)  # deadline already passed
    robot.receive(encode_wheels(WheelCommand(2, 100.9, 0.1, 0.1)), 100.03)  # its sequence number again
    robot.receive(b"garbage", 100.03)
    assert robot.counters.dropped["late"] == 1 and robot.counters.dropped["duplicate"] == 1
    assert robot.counters.dropped["malformed"] == 1 and robot.command == (0.2, 0.4)


def test_pacer_waits_for_each_point_and_counts_overruns() -> None:
    now = [10.0]

    def clock() -> float:  # every reading takes 1 us, as polling a real clock does
        now[0] += 1e-6
        return now[0]

    pacer = Pacer(clock=clock, sleep=lambda s: now.__setitem__(0, now[0] + s))
    pacer.start(0.0)
    pacer.wait_until(0.01)
    assert now[0] >= 10.01
    now[0] = 10.05  # the work of the next point took too long
    pacer.wait_until(0.02)
    pacer.wait_until(0.02)  # a second live component at the same point does not count again
    summary = pacer.summary()
    assert summary["points"] == 2 and summary["overruns"] == 1
    assert summary["overrun.max"] == pytest.approx(0.03, abs=1e-5)
    assert 0.0 <= pacer.lateness[0] < 1e-5  # on time: woke at the deadline, to the clock's resolution
    assert summary["jitter.max"] == pytest.approx(0.03, abs=1e-5)  # the overrun's point was 30 ms late


# -- real processes on 127.0.0.1 ---------------------------------------------------------------------

def endpoint(port: int) -> str:
    return f"tcp/127.0.0.1:{port}"


def _env() -> dict[str, str]:
    env = {**os.environ, "COLUMNS": "120", "NO_COLOR": "1", "TERM": "dumb"}
    env.pop("FORCE_COLOR", None)
    return env


@contextmanager
def emulator(port: int, tmp_path: Path, *options: str) -> Iterator[tuple[subprocess.Popen, Path]]:
    """``platoon m3pi-emulator`` for robot 3, listening on ``port``; its stderr goes to a file."""
    log = tmp_path / f"emulator-{port}.log"
    with open(log, "w") as stream:
        process = subprocess.Popen([str(PLATOON), "m3pi-emulator", "--config", str(LIVE3), "--set",
                                    f'vehicles.3.connect=["{endpoint(port)}"]', *options],
                                   cwd=REPO, env=_env(), stdout=stream, stderr=subprocess.STDOUT)
    try:
        deadline = time.monotonic() + 30
        while "configured, pose on" not in log.read_text():
            assert process.poll() is None, log.read_text()
            assert time.monotonic() < deadline, "the emulator did not start"
            time.sleep(0.05)
        yield process, log
    finally:
        if process.poll() is None:
            os.kill(process.pid, signal.SIGCONT)
            process.terminate()
            try:
                process.wait(10)
            except subprocess.TimeoutExpired:
                process.kill()
                process.wait()


def start_run(port: int, trace: Path, stop_time: float, *sets: str) -> subprocess.Popen:
    """``platoon run`` of LIVE3 with robot 3 at ``port``; SIGINT at its default, as a user's shell gives it
    (a test run started in the background hands down SIGINT ignored, and the run keeps what it is given)."""
    arguments = [str(PLATOON), "run", str(LIVE3), "--out", str(trace), "--set", f"simulation.stop_time={stop_time}",
                 "--set", f'vehicles.3.connect=["{endpoint(port)}"]']
    for assignment in sets:
        arguments += ["--set", assignment]
    return subprocess.Popen(arguments, cwd=REPO, env=_env(), stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))


def finish(process: subprocess.Popen, timeout: float = 120) -> tuple[int, str, str]:
    out, err = process.communicate(timeout=timeout)
    return process.returncode, out, err


def wait_for(condition: Callable[[], object], what: str | Callable[[], str], process: subprocess.Popen | None = None,
             seconds: float = 60) -> None:
    """Until ``condition()`` holds (an event, never a guess at how long it takes): fails naming ``what``
    (a text, or a function giving it then) after ``seconds``, or at once if ``process`` (the run) ended meanwhile."""
    deadline = time.monotonic() + seconds
    while not condition():
        said = what() if callable(what) else what
        if process is not None and process.poll() is not None:
            raise AssertionError(f"the run ended while waiting until {said}: {process.communicate()}")
        assert time.monotonic() < deadline, f"not within {seconds:g} s: {said}"
        time.sleep(0.02)


def wait_for_running(log: Path, process: subprocess.Popen) -> None:
    """Until the run steps the robot: the emulator took its first wheel command."""
    wait_for(lambda: "-> running (command" in log.read_text(), "the emulator runs on the run's commands", process)


def link_counters(trace: Path, scratch: Path) -> dict[str, float]:
    """Robot 3's newest link counters in what the running run's trace holds so far (its complete chunks,
    read as ``platoon trace recover`` reads a killed run's file)."""
    from orchestrator.trace import recover

    so_far = scratch / "so-far.mcap"
    recover(trace.with_name(trace.name + ".partial"), so_far)
    link = load(so_far).live.get("vehicle3/link", {})
    return {key: values[-1] for key, values in link.items() if key.startswith("pose.") and len(values)}


def test_live_robot_tracks_the_all_fmu_run(tmp_path: Path) -> None:
    """At zero noise and latency the live robot's platoon matches the all-FMU run to a few mm.

    Why not exactly: the robot's wheels get one command per 10 ms step and hold it (the FMU's model
    recomputes its command inside the step), poses are up to one 5 ms sampling period old and are
    dead-reckoned to the step's instant, and the pacing wakes up late by ~0.1 ms (at 0.35 m/s, 0.04 mm).
    Measured: 0.36 and 0.90 mm at most over 10 s (two runs); 3 mm leaves room for a loaded machine's jitter.
    """
    port = free_port()
    live, simulated = tmp_path / "live.mcap", tmp_path / "fmu.mcap"
    with emulator(port, tmp_path) as (_, log):
        first = start_run(port, live, 10.0)
        wait_for_running(log, first)
        second, _, refused = finish(start_run(port, tmp_path / "second.mcap", 2.0))  # one run per robot
        assert second == 1 and "robot 3 (platoon/m3pi/3) is already driven by another run" in refused, refused
        code, out, err = finish(first)
        assert code == 0, err
        again, _, err_again = finish(start_run(port, tmp_path / "again.mcap", 2.0))  # the same emulator, a new run
        assert again == 0, err_again
        assert "back on the initial pose" in log.read_text()
    assert "running -> stopped (stop command)" in log.read_text() or "host's liveliness token dropped" in log.read_text()
    reference = subprocess.run([str(PLATOON), "run", str(LIVE3), "-q", "--engine", "python", "--out", str(simulated),
                                "--set", "simulation.stop_time=10.0", "--set", "vehicles.3.endpoint=fmu"],
                               cwd=REPO, env=_env(), capture_output=True, text=True, timeout=120)
    assert reference.returncode == 0, reference.stderr
    a, b = load(live), load(simulated)
    for vehicle in a.vehicles():
        x, y = a.component(vehicle)["x"], a.component(vehicle)["y"]
        assert len(x) == len(b.component(vehicle)["x"]) == 1001
        distance = np.hypot(x - b.component(vehicle)["x"], y - b.component(vehicle)["y"])
        assert distance.max() < 3e-3, f"{vehicle}: {distance.max():.2e} m"
    # the live vehicle's raw link, its statistics and its states are in the same trace
    assert {"vehicle3/pose", "vehicle3/command", "vehicle3/link"} <= set(a.live)
    assert len(a.live["vehicle3/command"]["seq"]) >= 1000
    assert np.all(np.diff(a.live["vehicle3/pose"]["seq"]) > 0)
    messages = [line.message for line in a.log]
    for change in ("configured -> synchronized", "synchronized -> running", "running -> stopped"):
        assert any(change in m and "robot 3" in m for m in messages), change
    assert "pacing" in a.metadata["platoon.hil"] and "vehicle3" in a.metadata["platoon.hil"]
    assert "step jitter median" in out and "vehicle3" in out


def test_noisy_late_robot_still_converges(tmp_path: Path) -> None:
    """The paper's motion capture noise (2 mm, 2 deg) and 20 ms of latency on poses and on commands:
    every vehicle ends within 20 mm of the path (the all-FMU run converges by about 15 s)."""
    port = free_port()
    trace = tmp_path / "noisy.mcap"
    with emulator(port, tmp_path, "--noise-position", "0.002", "--noise-heading", "2", "--latency", "0.02",
                  "--command-latency", "0.02", "--seed", "7"):
        code, out, err = finish(start_run(port, trace, 20.0))
    assert code == 0, err
    loaded = load(trace)
    config = config_from_mapping(loaded.config)
    for vehicle in loaded.vehicles():
        channel = loaded.component(vehicle)
        last = channel["t"] > channel["t"][-1] - 1.0
        error = np.abs(path_errors(config, channel["x"][last], channel["y"][last])).max()
        assert error < 0.020, f"{vehicle}: {error * 1e3:.1f} mm off the path at the end"


@pytest.mark.parametrize("fault, reason", [
    (signal.SIGKILL, "lost: its liveliness token platoon/m3pi/3/alive was dropped"),  # gone from the network
    (signal.SIGSTOP, "lost: no valid pose for"),  # alive on the network (its lease holds), but silent
], ids=["killed", "frozen"])
def test_lost_robot_ends_the_run_within_5_s_with_a_stop_and_a_finalized_trace(
        tmp_path: Path, fault: signal.Signals, reason: str) -> None:
    port = free_port()
    trace = tmp_path / "lost.mcap"
    with emulator(port, tmp_path) as (robot, log):
        run = start_run(port, trace, 60.0)
        wait_for_running(log, run)
        os.kill(robot.pid, fault)
        struck = time.monotonic()
        code, _, err = finish(run, timeout=30)
        ended = time.monotonic() - struck
    assert code == 1 and ended < 5.0, (code, ended, err)
    assert f"robot 3 (platoon/m3pi/3) {reason}" in err and "Traceback" not in err, err
    loaded = load(trace)
    assert loaded.run["status"] == "failed" and "robot 3" in loaded.run["error"]
    commands = loaded.live["vehicle3/command"]
    last = int(np.argmax(commands["seq"]))  # the newest command: a stop (records at one time may come in any order)
    assert commands["left"][last] == 0.0 and commands["right"][last] == 0.0
    assert any("-> error" in line.message for line in loaded.log)


def test_garbage_on_the_pose_key_is_counted_and_ignored_and_ctrl_c_stops_the_robot(tmp_path: Path) -> None:
    """A third session publishes every kind of bad pose to the run; the run drops and counts each,
    the robot keeps its path; SIGINT ends the run with exit 130 after a stop command reached the robot.

    Every wait is for an event: the attacker's publisher matched by the run's subscriber, real poses
    from the emulator, the counters in the run's trace. Poses may arrive up to 2 s old (``hil.max_pose_age``,
    0.25 s by default) so that a loaded machine's delays make no real pose late: the counts are exact.
    Commands, the stop included, are valid for 2 s (``hil.command_validity``, 0.1 s by default): on a
    loaded machine a stop can take longer than 0.1 s to reach the robot, which then drops it as late
    and stops only when the run's liveliness token goes (seen: "running -> stopped (host's liveliness
    token dropped)").
    """
    import json

    from bridge.session import open_session, zenoh_config

    port, host_port = free_port(), free_port()
    trace = tmp_path / "garbage.mcap"
    with emulator(port, tmp_path) as (_, log):
        run = start_run(port, trace, 60.0, f'vehicles.3.listen=["{endpoint(host_port)}"]', "hil.max_pose_age=2.0",
                        "hil.command_validity=2.0")
        wait_for_running(log, run)
        # the attacker's session meets the run (its listen port) and the emulator, to replay real poses
        with open_session(zenoh_config(connect=[endpoint(host_port), endpoint(port)]), "test") as session:
            attacker = session.declare_publisher(KEYS.pose, allowed_destination=zenoh.Locality.REMOTE)
            wait_for(lambda: attacker.matching_status.matching, "the run subscribes to what the attacker publishes", run)
            real: list[bytes] = []  # the emulator's poses, as the attacker hears them
            subscriber = session.declare_subscriber(KEYS.pose, lambda sample: real.append(sample.payload.to_bytes()))
            wait_for(lambda: real, "the emulator's poses reach the attacker", run)
            good = encode_pose(Pose(1, 0, time.time(), 0.0, 0.0, 0.0))
            garbage = {
                "oversized": [bytes(1000)] * 3,
                "malformed": [good[:-4], good + b"\0"],
                "version": [b"\x07" + good[1:]],
                "non_finite": [encode_pose(Pose(2**31, 0, time.time(), math.nan, 0.0, 0.0)),
                               encode_pose(Pose(2**31, 0, time.time(), 0.0, 0.0, math.inf))],
                "late": [encode_pose(Pose(2**31, 0, time.time() - 5.0, 9.0, 9.0, 0.0))],
            }
            for payloads in garbage.values():
                for payload in payloads:
                    attacker.put(payload)
            heard = len(real)
            wait_for(lambda: len(real) >= heard + 5, "five more real poses", run)
            replayed = real[heard:heard + 5]  # the run took each already (or takes it next): duplicates or out of order
            for payload in replayed:
                attacker.put(payload)
            subscriber.undeclare()
            expected = {f"pose.dropped.{reason}": len(payloads) for reason, payloads in garbage.items()}
            counters: dict[str, float] = {}

            def all_counted() -> bool:
                counters.update(link_counters(trace, tmp_path))
                replays = counters.get("pose.dropped.duplicate", 0) + counters.get("pose.dropped.out_of_order", 0)
                return replays >= len(replayed) and all(counters.get(k, 0) >= n for k, n in expected.items())

            wait_for(all_counted, lambda: f"the run's trace counts every drop (so far {counters})", run)
        run.send_signal(signal.SIGINT)
        code, _, err = finish(run, timeout=60)
        wait_for(lambda: "robot 3: running -> stopped (stop command)" in log.read_text(),
                 lambda: f"the robot stopped: {log.read_text()}")
    assert code == 130, err
    loaded = load(trace)
    stats = json.loads(loaded.metadata["platoon.hil"]["vehicle3"])
    for reason, payloads in garbage.items():
        assert stats[f"pose.dropped.{reason}"] == len(payloads), (reason, stats)
    assert stats["pose.dropped.duplicate"] + stats["pose.dropped.out_of_order"] == len(replayed), stats
    assert loaded.live["vehicle3/link"]["pose.dropped.oversized"][-1] == 3
    assert any("dropped a message" in line.message for line in loaded.log)
    config = config_from_mapping(loaded.config)
    robot = loaded.component("vehicle3")
    assert np.abs(path_errors(config, robot["x"], robot["y"])).max() < 0.035  # never steered off (0.029 at start)


def test_missing_robot_fails_the_run_with_a_clear_message(tmp_path: Path) -> None:
    port = free_port()
    trace = tmp_path / "missing.mcap"
    code, _, err = finish(start_run(port, trace, 5.0, "hil.connect_timeout=1.0"), timeout=60)
    assert code == 1
    assert "robot 3 (platoon/m3pi/3) did not appear within 1 s: no liveliness token on platoon/m3pi/3/alive" in err
    assert load(trace).run["status"] == "failed"


def test_live_run_options_that_cannot_work_are_usage_errors(tmp_path: Path) -> None:
    result = subprocess.run([str(PLATOON), "run", str(LIVE3), "--engine", "native", "--out", str(tmp_path / "x.mcap")],
                            cwd=REPO, env=_env(), capture_output=True, text=True, timeout=60)
    assert result.returncode == 2
    assert "vehicle3 is a live robot" in result.stderr and "python engine" in result.stderr
    result = subprocess.run([str(PLATOON), "m3pi-emulator", "--config", str(REPO / "configs/paper/m3pi.toml")],
                            cwd=REPO, env=_env(), capture_output=True, text=True, timeout=60)
    assert result.returncode == 2 and "no live vehicle" in result.stderr
