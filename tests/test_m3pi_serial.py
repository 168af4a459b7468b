"""The real robot's side of the m3pi link (bridge.serial_endpoint): the motor byte encoding, and the
endpoint end to end on a pseudo-terminal standing in for the XBee, with real Zenoh sessions on 127.0.0.1.
"""

from __future__ import annotations

import math
import os
import queue
import select
import socket
import threading
import time
import tty
from pathlib import Path
from contextlib import contextmanager
from typing import Iterator

import pytest
import zenoh

from bridge.claim import CLAIM_LEASE, LeaseRenewal, claim_text
from bridge.lab_key import LabKey
from bridge.protocol import LinkCounters, RobotKeys, WheelCommand, decode_status, encode_wheels
from bridge.serial_endpoint import (
    SEND_SIGNATURE,
    STOP_FRAME,
    SerialEndpointError,
    SpeedScale,
    decode_motor_bytes,
    describe_signature,
    motor_bytes,
    open_serial_port,
    read_signature,
    run_serial_endpoint,
)
from bridge.session import SessionError, open_session, zenoh_config

WAIT = 5.0  # s: the most any single expected event may take (it normally takes milliseconds)

from tests.conftest import free_port


# ---------------------------------------------------------------- encoder


@pytest.mark.parametrize("scale", [
    SpeedScale(),
    SpeedScale(max_speed=0.6),
    SpeedScale.from_options(max_speed=0.8, swap_motors=True),
    SpeedScale(invert_left=True),
    SpeedScale(left_motor="M2", right_motor="M1", invert_right=True),
])
def test_motor_bytes_round_trip(scale: SpeedScale) -> None:
    speeds = [(0.0, 0.0), (0.5, -0.5), (-0.123, 0.987), (scale.max_speed, -scale.max_speed), (-0.001, 0.3)]
    for left, right in speeds:
        left, right = max(-scale.max_speed, min(scale.max_speed, left)), max(-scale.max_speed, min(scale.max_speed, right))
        frame = motor_bytes(left, right, scale)
        assert len(frame) == 4 and frame[0] in (0xC1, 0xC2) and frame[2] in (0xC5, 0xC6)
        [(got_left, got_right)] = decode_motor_bytes(frame, scale)
        assert abs(got_left - left) <= scale.quantum / 2 + 1e-12
        assert abs(got_right - right) <= scale.quantum / 2 + 1e-12


def test_motor_bytes_layout() -> None:
    """The exact bytes the 3pi serial slave expects, M1 (left on a stock 3pi) first."""
    assert motor_bytes(0.0, 0.0) == STOP_FRAME == bytes.fromhex("C1 00 C5 00")
    assert motor_bytes(1.0, -1.0) == bytes.fromhex("C1 7F C6 7F")
    assert motor_bytes(-0.5, 0.25) == bytes((0xC2, 64, 0xC5, 32))
    # A speed that rounds to byte 0 is a stop on the forward opcode, whatever its sign.
    assert motor_bytes(-0.001, -0.0) == STOP_FRAME


def test_motor_bytes_clip_swap_invert() -> None:
    assert motor_bytes(3.0, -7.5) == bytes.fromhex("C1 7F C6 7F")
    assert decode_motor_bytes(motor_bytes(3.0, -7.5)) == [(1.0, -1.0)]
    half = SpeedScale(max_speed=0.5)
    assert motor_bytes(0.5, 0.25, half) == motor_bytes(1.0, 0.5)
    # Swapped: the left wheel's speed goes to M2.
    swapped = SpeedScale.from_options(swap_motors=True)
    assert motor_bytes(1.0, -0.5, swapped) == bytes((0xC2, 64, 0xC5, 127))
    assert decode_motor_bytes(bytes((0xC2, 64, 0xC5, 127)), swapped) == [(1.0, -64 / 127)]
    # Inverted left motor: a forward left wheel is M1 backward.
    assert motor_bytes(1.0, 1.0, SpeedScale(invert_left=True)) == bytes.fromhex("C2 7F C5 7F")
    assert motor_bytes(1.0, 1.0, SpeedScale(invert_right=True)) == bytes.fromhex("C1 7F C6 7F")
    # Several frames decode in order.
    stream = motor_bytes(0.2, 0.4) + STOP_FRAME + motor_bytes(-1.0, 1.0)
    assert [(round(l, 2), round(r, 2)) for l, r in decode_motor_bytes(stream)] == [(0.2, 0.4), (0.0, 0.0), (-1.0, 1.0)]


@pytest.mark.parametrize("data, problem", [
    (bytes.fromhex("81 00 C5 00"), "byte 0x81 at offset 0 is not an M1 opcode"),
    (bytes.fromhex("C1 00 C1 00"), "byte 0xc1 at offset 2 is not an M2 opcode"),
    (STOP_FRAME + bytes.fromhex("C1 80 C5 00"), "byte 0x80 at offset 5 after the M1 opcode is not a speed byte"),
    (STOP_FRAME + bytes.fromhex("C1 10 C5"), "the frame at offset 4 has 3 bytes, expected 4"),
])
def test_decode_motor_bytes_rejects_garbage(data: bytes, problem: str) -> None:
    with pytest.raises(ValueError, match=problem):
        decode_motor_bytes(data)


def test_bad_scale_and_speeds_are_refused() -> None:
    with pytest.raises(ValueError, match="max_speed = 0"):
        SpeedScale(max_speed=0)
    with pytest.raises(ValueError, match="one to be 'M1' and the other 'M2'"):
        SpeedScale(left_motor="M1", right_motor="M1")
    with pytest.raises(ValueError, match="right wheel speed nan is not finite"):
        motor_bytes(0.1, math.nan)


# ---------------------------------------------------------------- serial port


class Pty:
    """A pseudo-terminal: the endpoint opens ``path`` as its serial port, the test reads ``master``."""

    def __init__(self) -> None:
        self.master, self.slave = os.openpty()
        tty.setraw(self.master)
        self.path = os.ttyname(self.slave)

    def read(self, count: int, timeout: float = WAIT) -> bytes:
        """Exactly ``count`` bytes, or fail after ``timeout`` s saying what did come."""
        data = b""
        deadline = time.monotonic() + timeout
        while len(data) < count:
            left = deadline - time.monotonic()
            if left <= 0 or not select.select([self.master], [], [], left)[0]:
                raise AssertionError(f"pty {self.path}: {len(data)} of {count} bytes in {timeout} s: {data.hex(' ')}")
            data += os.read(self.master, count - len(data))
        return data

    def pending(self, wait: float = 0.0) -> bytes:
        """Whatever arrives within ``wait`` s (nothing blocks longer)."""
        data = b""
        while select.select([self.master], [], [], wait)[0]:
            data += os.read(self.master, 4096)
            wait = 0.0
        return data

    def close(self) -> None:
        os.close(self.master)
        os.close(self.slave)


@pytest.fixture
def pty() -> Iterator[Pty]:
    pty = Pty()
    yield pty
    pty.close()


def test_missing_port_names_it() -> None:
    with pytest.raises(SerialEndpointError, match="serial port /dev/no-such-xbee: cannot open it at 115200 baud"):
        run_serial_endpoint("/dev/no-such-xbee", 1, listen=["tcp/127.0.0.1:1"])


def test_signature_query(pty: Pty) -> None:
    """0x81 goes out; the answer is read if the robot gives one, and silence is not an error."""
    with open_serial_port(pty.path) as link:
        started = time.monotonic()
        assert read_signature(link, timeout=0.2) == b""
        assert 0.15 <= time.monotonic() - started < 2.0
        assert pty.read(1) == bytes((SEND_SIGNATURE,))

        answer = threading.Thread(target=lambda: (pty.read(1), os.write(pty.master, b"3pi1.0")))
        answer.start()
        assert read_signature(link, timeout=WAIT) == b"3pi1.0"
        answer.join(WAIT)
    assert "no answer to the signature query (0x81)" in describe_signature(b"", pty.path)
    assert describe_signature(b"3pi1.0", pty.path) == f"robot signature '3pi1.0' on {pty.path}"
    assert "unexpected answer" in describe_signature(b"\xff\x00", pty.path)


# ---------------------------------------------------------------- end to end


class Endpoint:
    """``run_serial_endpoint`` in a background thread; ``stop()`` returns its counters or re-raises."""

    def __init__(self, **kwargs) -> None:
        self.stop_event = threading.Event()
        self.result: LinkCounters | BaseException | None = None
        self.thread = threading.Thread(target=self._run, kwargs=kwargs, daemon=True)
        self.thread.start()

    def _run(self, **kwargs) -> None:
        try:
            self.result = run_serial_endpoint(stop_event=self.stop_event, **kwargs)
        except BaseException as error:  # handed to the test thread
            self.result = error

    def stop(self) -> LinkCounters:
        self.stop_event.set()
        self.thread.join(WAIT)
        assert not self.thread.is_alive(), "the serial endpoint did not stop within its wait"
        if isinstance(self.result, BaseException):
            raise self.result
        assert isinstance(self.result, LinkCounters)
        return self.result


@contextmanager
def host_session(port: int) -> Iterator[zenoh.Session]:
    with open_session(zenoh_config(connect=[f"tcp/127.0.0.1:{port}"]), "test host") as session:
        yield session


def wait_for_token(session: zenoh.Session, key: str) -> None:
    seen: queue.Queue[zenoh.SampleKind] = queue.Queue()
    with session.liveliness().declare_subscriber(key, lambda sample: seen.put(sample.kind), history=True):
        assert seen.get(timeout=WAIT) == zenoh.SampleKind.PUT, f"no liveliness token at {key}"


class StderrLog:
    """The endpoint's stderr lines as they come (capsys hands out only what is new on each call)."""

    def __init__(self, capsys: pytest.CaptureFixture[str]) -> None:
        self.capsys = capsys
        self.text = ""

    def wait_for(self, line: str, timeout: float = WAIT) -> None:
        deadline = time.monotonic() + timeout
        while line not in self.read():
            assert time.monotonic() < deadline, f"no stderr line with {line!r} in {timeout} s; got:\n{self.text}"
            time.sleep(0.01)

    def read(self) -> str:
        self.text += self.capsys.readouterr().err
        return self.text


CLAIM = 0x00C0_FFEE_0000_0003
LAB_KEY = LabKey(bytes(range(32)), Path("lab.key"))


def request_claim(publisher, keys: RobotKeys, claim: int, key: LabKey | None = LAB_KEY) -> None:
    """A run's claim request (command 0, speeds 0), with the MAC of ``key``."""
    publisher.put(encode_wheels(WheelCommand(0, time.time() + 1.0, 0.0, 0.0, claim), key, keys.wheels))


def test_serial_endpoint_end_to_end(pty: Pty, capsys: pytest.CaptureFixture[str]) -> None:
    scale = SpeedScale(max_speed=0.8)
    # The endpoint's command timeout, far from the deadlines below: each stop's cause is the one its log
    # line names, and the bounds on when it came follow from the protocol (never before the cause, and
    # before the next cause could act), not from how fast this machine is.
    timeout = 2.0  # s
    port = free_port()
    keys = RobotKeys("e2e", 3)
    log = StderrLog(capsys)
    endpoint = Endpoint(port=pty.path, robot=3, prefix="e2e", listen=[f"tcp/127.0.0.1:{port}"], scale=scale,
                        command_timeout=timeout, lab_key=LAB_KEY)
    try:
        # Start-up: the signature query (the pty answers nothing), then a stop.
        assert pty.read(1) == bytes((SEND_SIGNATURE,))
        assert pty.read(4) == STOP_FRAME

        with host_session(port) as session:
            wait_for_token(session, keys.alive)
            host_token = session.liveliness().declare_token(keys.host(CLAIM))
            statuses: queue.Queue[bytes] = queue.Queue()
            status_subscriber = session.declare_subscriber(keys.status, lambda s: statuses.put(s.payload.to_bytes()))
            publisher = session.declare_publisher(keys.wheels, congestion_control=zenoh.CongestionControl.BLOCK)
            seq = 0

            def command(left: float, right: float, deadline_in: float = 2.0) -> float:
                nonlocal seq
                seq += 1
                sent = time.time()
                publisher.put(encode_wheels(WheelCommand(seq, sent + deadline_in, left, right, CLAIM), LAB_KEY, keys.wheels))
                return sent

            request_claim(publisher, keys, CLAIM)
            log.wait_for("configured -> synchronized (host present)")
            renewal = LeaseRenewal(lambda: request_claim(publisher, keys, CLAIM))  # as a run renews its claim

            def expect(left: float, right: float) -> float:
                """The next frame on the wire is this command (speeds clipped to max_speed)."""
                [(got_left, got_right)] = decode_motor_bytes(pty.read(4), scale)
                clip = lambda v: max(-scale.max_speed, min(scale.max_speed, v))  # noqa: E731
                assert abs(got_left - clip(left)) <= scale.quantum and abs(got_right - clip(right)) <= scale.quantum, \
                    f"commanded ({left}, {right}), the motors got ({got_left}, {got_right})"
                return time.time()

            # Commands reach the motors, one frame each, in order.
            for left, right in [(0.5, 0.5), (-0.3, 0.7), (0.123, -0.456), (2.0, -3.0), (0.0, 0.8)]:
                command(left, right)
                expect(left, right)
            assert "synchronized -> running (valid command 1)" in log.read()
            status = decode_status(statuses.get(timeout=WAIT))  # the claim, reported 20 times a second
            while status.accepted < 5:
                status = decode_status(statuses.get(timeout=WAIT))
            assert (status.owner, status.applied, status.accepted, status.foreign) == (CLAIM, 5, 5, 0)

            # Malformed, duplicate, late and foreign commands are dropped: the next frame is the next valid command.
            publisher.put(b"\x01\x02garbage")
            publisher.put(encode_wheels(WheelCommand(seq, time.time() + 2.0, -0.8, -0.8, CLAIM), LAB_KEY,
                                        keys.wheels))  # seq again
            publisher.put(encode_wheels(WheelCommand(2**32 - 1, time.time() + 2.0, 0.8, 0.8, CLAIM + 1)))  # no key
            command(0.7, 0.7, deadline_in=-1.0)  # deadline already passed
            command(-0.2, 0.2)
            expect(-0.2, 0.2)  # the next frame, so the three before it wrote none

            # No command for the command timeout: stopped, before the deadline 1 s later could stop it
            # (a late watchdog would leave that to the deadline, whose log line differs).
            sent = command(0.4, 0.4, deadline_in=timeout + 1.0)
            expect(0.4, 0.4)
            assert decode_motor_bytes(pty.read(4, timeout=timeout + WAIT), scale) == [(0.0, 0.0)]
            stopped_after = time.time() - sent
            assert timeout - 0.05 <= stopped_after < timeout + 1.0, f"stopped {stopped_after:.3f} s after the command"
            log.wait_for(f"running -> stopped (no valid command for {timeout:g} s)")

            # A deadline shorter than the timeout: stopped at the deadline; fresh commands restart first.
            sent = command(0.3, -0.3, deadline_in=0.3)
            expect(0.3, -0.3)
            assert decode_motor_bytes(pty.read(4, timeout=WAIT), scale) == [(0.0, 0.0)]
            stopped_after = time.time() - sent
            assert 0.3 <= stopped_after < timeout, f"stopped {stopped_after:.3f} s after the command"
            log.wait_for(f"running -> stopped (command deadline passed, seq {seq})")
            assert f"stopped -> running (valid command {seq})" in log.read()

            # The host goes away: stopped at once, before the command's deadline (5 s: at most MAX_COMMAND_AHEAD) or the timeout.
            sent = command(0.6, 0.6, deadline_in=5.0)
            expect(0.6, 0.6)
            renewal.stop()
            host_token.undeclare()
            assert pty.read(4, timeout=WAIT) == STOP_FRAME
            assert time.time() - sent < timeout, "the stop came from the watchdog, not from the host's token"
            log.wait_for("running -> stopped (claim ended: its token")

            # A run that goes silent while a copy of its token stays (a keyless client's): its lease ends the claim.
            second = CLAIM + 1
            copy = session.liveliness().declare_token(keys.host(second))
            request_claim(publisher, keys, second)
            log.wait_for(f"claimed by {claim_text(second)}")
            publisher.put(encode_wheels(WheelCommand(1, time.time() + 5.0, 0.6, 0.6, second), LAB_KEY, keys.wheels))
            expect(0.6, 0.6)
            silent = time.time()
            assert pty.read(4, timeout=CLAIM_LEASE + WAIT) == STOP_FRAME  # the lease's end (or the equal timeout)
            assert time.time() - silent < CLAIM_LEASE + 1.0
            log.wait_for(f"claim {claim_text(second)} released (its lease of {CLAIM_LEASE:g} s ran out)")
            assert pty.pending(0.3) in (b"", STOP_FRAME)  # the other of the two stops, as close as 2 s and 2 s
            copy.undeclare()
            publisher.undeclare()
            status_subscriber.undeclare()

        counters = endpoint.stop()
    finally:
        endpoint.stop_event.set()
        endpoint.thread.join(WAIT)

    # Exit: the motors are zeroed once more before the port closes.
    assert pty.pending(0.2) == STOP_FRAME
    assert counters.accepted == seq  # every command but the late one, and the silent run's one
    assert counters.dropped["malformed"] == 1
    assert counters.dropped["duplicate"] == 1
    assert counters.dropped["late"] == 1
    assert counters.dropped["unauthenticated"] == 1
    assert counters.received == counters.accepted + 4
    text = log.read()
    assert "no answer to the signature query (0x81)" in text
    assert "wheel commands received" in text and "dropped 4 (malformed 1, duplicate 1, late 1, unauthenticated 1)" in text


def test_motors_zeroed_when_zenoh_fails(pty: Pty) -> None:
    """A Zenoh failure after the port opened still leaves the motors at zero before the port closes."""
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        port = taken.getsockname()[1]
        with pytest.raises(SessionError, match="m3pi-serial robot 2: cannot open a Zenoh session"):
            run_serial_endpoint(pty.path, 2, listen=[f"tcp/127.0.0.1:{port}"])
    assert pty.pending(0.2) == bytes((SEND_SIGNATURE,)) + STOP_FRAME + STOP_FRAME


def test_a_stranger_without_the_lab_key_writes_no_motor_frame(pty: Pty, capsys: pytest.CaptureFixture[str]) -> None:
    """The hostile round's case: a client of m3pi-serial's port that reads nothing declares its own host token,
    asks for the claim and sends 1 s of full-speed commands at 200 Hz (no MAC, and a MAC of another key).
    Not one motor frame reaches the serial port after the start-up stop; a run of the lab then claims it."""
    port = free_port()
    keys = RobotKeys("e2e", 3)
    log = StderrLog(capsys)
    endpoint = Endpoint(port=pty.path, robot=3, prefix="e2e", listen=[f"tcp/127.0.0.1:{port}"], lab_key=LAB_KEY)
    try:
        assert pty.read(1) == bytes((SEND_SIGNATURE,)) and pty.read(4) == STOP_FRAME
        with host_session(port) as session:
            wait_for_token(session, keys.alive)
            token = session.liveliness().declare_token(keys.host(CLAIM + 1))  # noqa: F841 (held)
            publisher = session.declare_publisher(keys.wheels, congestion_control=zenoh.CongestionControl.BLOCK)
            deadline = time.monotonic() + WAIT
            while not publisher.matching_status.matching:  # the stranger's commands do reach the robot side
                assert time.monotonic() < deadline, "the robot side does not subscribe to the stranger's key"
                time.sleep(0.01)
            theirs = LabKey(bytes(32), Path("theirs.key"))
            for seq in range(1, 201):
                key = None if seq % 2 else theirs
                request_claim(publisher, keys, CLAIM + 1, key)
                publisher.put(encode_wheels(WheelCommand(seq * 2**22, time.time() + 2.0, 1.0, 1.0, CLAIM + 1), key,
                                            keys.wheels))
                time.sleep(0.005)
            log.wait_for("(first 'unauthenticated' drop")
            assert pty.pending(0.5) == b"", "a motor frame of the stranger reached the robot"
            request_claim(publisher, keys, CLAIM)  # a run of the lab, meanwhile: its request before its token
            run_token = session.liveliness().declare_token(keys.host(CLAIM))  # noqa: F841 (held)
            log.wait_for(f"claimed by {CLAIM:016x}")
        counters = endpoint.stop()
    finally:
        endpoint.stop_event.set()
        endpoint.thread.join(WAIT)
    assert counters.dropped["unauthenticated"] == 400 and counters.accepted == 0
    assert "claimed by 00c0ffee00000004" not in log.read()
