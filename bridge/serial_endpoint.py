"""The real robot's side of the m3pi link: wheel commands from Zenoh to a Pololu 3pi over an XBee.

The m3pi is a 3pi base running Pololu's 3pi serial slave program, reached through an XBee in
transparent mode: whatever bytes this program writes to the XBee's serial port come out of the
robot's XBee into the 3pi's UART (115200 baud, 8N1). This endpoint stands for the robot on Zenoh: it
declares the robot's liveliness token, obeys the first run that claims it with the lab key
(``bridge.claim``, ``bridge.lab_key``) until that claim ends (the run's MAC'd release, its lease not renewed,
or its token gone), checks every wheel command (decode, claim, sequence, deadline) and writes the owner's
valid ones as motor bytes at once; it reports its claim and counts on the status key.

Byte format (3pi serial slave, a TReX-like command set: an opcode 0x80..0xFF, then data bytes
0x00..0x7F):

* one motor frame is 4 bytes, M1 first: ``M1-opcode speed M2-opcode speed``
* ``0xC1`` / ``0xC2`` = M1 forward / backward, ``0xC5`` / ``0xC6`` = M2 forward / backward; the
  speed byte is 0..127 (the 3pi maps 127 to full PWM)
* speed byte = round(|v| / max_speed * 127), clipped to 127; the sign of v picks the opcode; a byte
  of 0 always uses the forward opcode, so the stop frame is exactly ``C1 00 C5 00``
* ``0x81`` is the serial slave's "send signature" query, not a stop (a stop is a zero speed command,
  above). It is sent once at start-up, and the answer (6 ASCII bytes
  such as ``3pi1.0``) is logged, which tells that the robot is on the air and runs the slave
  program. No answer is logged, not fatal: a pseudo-terminal in the tests answers nothing, and the
  XBee may still be associating.

Safety: the motors are zeroed at start-up (the slave keeps running its last speeds, possibly from an
earlier session), when the current command's deadline passes, when no valid command came for
``command_timeout`` s, when the claim ends (release, lease, the host's liveliness token), and always on exit before the
port closes. The serial slave has no watchdog of its own, so a lost stop frame (transparent mode has
no end-to-end acknowledgement) leaves the robot running until the next frame: keep the robot in
reach of the XBee.

To be measured on the real robot (the defaults are estimates, see ``fmus.model.dynamics``):

* the speed scale: the wheel speed (m/s) at byte 127, ``SpeedScale.max_speed`` (default
  ``M3PI_WHEEL_SPEED_MAX`` = 1.0 m/s); the mapping is assumed linear, which the 3pi's open-loop PWM
  only approximates (dead band near zero, battery voltage);
* which motor is the left one (M1 on a stock 3pi; ``--swap-motors`` if not) and each motor's
  polarity (``invert_left`` / ``invert_right`` for a motor wired backwards);
* the track (distance between the wheels), which lives in the platoon config's ``[m3pi]`` table,
  not here: this endpoint only sees wheel speeds.
"""

from __future__ import annotations

import math
import sys
import threading
import time
from dataclasses import dataclass
from typing import Literal, Sequence

import serial
import zenoh

from bridge.claim import RobotClaim, claim_from_key, claim_text
from bridge.lab_key import LabKey, load_lab_key
from bridge.protocol import (
    DEFAULT_PREFIX,
    Drop,
    LinkCounters,
    MessageError,
    RobotKeys,
    WheelCommand,
    check_prefix,
    encode_status,
)
from bridge.session import open_session, zenoh_config
from bridge.states import LinkState, StateMachine
from fmus.model.dynamics import M3PI_WHEEL_SPEED_MAX

Motor = Literal["M1", "M2"]

SEND_SIGNATURE = 0x81
SIGNATURE_LENGTH = 6  # "3pi1.0": the serial slave answers exactly six ASCII bytes
SIGNATURE_TIMEOUT = 0.2  # s
M1_FORWARD, M1_BACKWARD = 0xC1, 0xC2
M2_FORWARD, M2_BACKWARD = 0xC5, 0xC6
SPEED_BYTE_MAX = 127
FRAME_SIZE = 4
STOP_FRAME = bytes((M1_FORWARD, 0, M2_FORWARD, 0))

DEFAULT_BAUD = 115200
DEFAULT_COMMAND_TIMEOUT = 0.25  # s
WATCHDOG_PERIOD = 0.02  # s
STATUS_PERIOD = 0.05  # s between two status messages (and one at once when the claim changes)
# A 4-byte frame takes 0.35 ms at 115200 baud; a write still blocked after this long means the port
# is gone or stuck, and the endpoint stops rather than hold the lock the watchdog needs.
WRITE_TIMEOUT = 0.1  # s

_OPCODES: dict[Motor, tuple[int, int]] = {"M1": (M1_FORWARD, M1_BACKWARD), "M2": (M2_FORWARD, M2_BACKWARD)}


class SerialEndpointError(RuntimeError):
    """The serial endpoint cannot go on (port missing or failing, bad setting); the text says which."""


@dataclass(frozen=True)
class SpeedScale:
    """How wheel speeds (m/s) become motor bytes: the constants to measure on the real robot.

    ``max_speed`` is the wheel speed at speed byte 127; faster commands are clipped to it. The
    left wheel is driven by ``left_motor`` (M1 on a stock 3pi) and the right by ``right_motor``;
    ``invert_left``/``invert_right`` flip a motor that is wired backwards.
    """

    max_speed: float = M3PI_WHEEL_SPEED_MAX
    left_motor: Motor = "M1"
    right_motor: Motor = "M2"
    invert_left: bool = False
    invert_right: bool = False

    def __post_init__(self) -> None:
        if not (math.isfinite(self.max_speed) and self.max_speed > 0):
            raise ValueError(f"speed scale: max_speed = {self.max_speed} m/s, expected a finite speed > 0")
        motors = (self.left_motor, self.right_motor)
        if set(motors) != {"M1", "M2"}:
            raise ValueError(f"speed scale: left_motor = {self.left_motor!r}, right_motor = {self.right_motor!r}; "
                             "expected one to be 'M1' and the other 'M2'")

    @classmethod
    def from_options(cls, max_speed: float = M3PI_WHEEL_SPEED_MAX, swap_motors: bool = False,
                     invert_left: bool = False, invert_right: bool = False) -> SpeedScale:
        """The scale the command line describes (``--max-speed``, ``--swap-motors``: M2 drives the left
        wheel; ``--invert-left``/``--invert-right``: a motor wired backwards)."""
        left, right = ("M2", "M1") if swap_motors else ("M1", "M2")
        return cls(max_speed, left, right, invert_left, invert_right)

    @property
    def quantum(self) -> float:
        """The speed one step of the speed byte stands for (m/s): the encoder's resolution."""
        return self.max_speed / SPEED_BYTE_MAX


def _speed_byte(speed: float, max_speed: float) -> int:
    return min(SPEED_BYTE_MAX, round(abs(speed) / max_speed * SPEED_BYTE_MAX))


def motor_bytes(left: float, right: float, scale: SpeedScale = SpeedScale()) -> bytes:
    """One 4-byte motor frame (M1 opcode, speed, M2 opcode, speed) for wheel speeds in m/s.

    Pure and I/O-free so that the encoding is tested without a robot. Non-finite speeds are refused
    here even though ``decode_wheels`` already drops them: a NaN must never reach a motor.
    """
    for name, value in (("left", left), ("right", right)):
        if not math.isfinite(value):
            raise ValueError(f"motor bytes: {name} wheel speed {value} is not finite")
    by_motor: dict[Motor, float] = {
        scale.left_motor: -left if scale.invert_left else left,
        scale.right_motor: -right if scale.invert_right else right,
    }
    frame = bytearray()
    for motor in ("M1", "M2"):
        speed = by_motor[motor]
        forward, backward = _OPCODES[motor]
        byte = _speed_byte(speed, scale.max_speed)
        frame += bytes((backward if speed < 0 and byte > 0 else forward, byte))
    return bytes(frame)


def _motor_speed(data: bytes, offset: int, motor: Motor, max_speed: float) -> float:
    forward, backward = _OPCODES[motor]
    opcode, byte = data[offset], data[offset + 1]
    if opcode not in (forward, backward):
        raise ValueError(f"motor bytes: byte {opcode:#04x} at offset {offset} is not an {motor} opcode "
                         f"(expected {forward:#04x} forward or {backward:#04x} backward)")
    if byte > SPEED_BYTE_MAX:
        raise ValueError(f"motor bytes: byte {byte:#04x} at offset {offset + 1} after the {motor} opcode is not a "
                         f"speed byte (0..{SPEED_BYTE_MAX})")
    return (-1.0 if opcode == backward else 1.0) * byte / SPEED_BYTE_MAX * max_speed


def decode_motor_bytes(data: bytes, scale: SpeedScale = SpeedScale()) -> list[tuple[float, float]]:
    """Wheel speeds (left, right) in m/s of each motor frame in ``data``: the inverse of ``motor_bytes``
    (up to the speed byte's resolution), for tests and for reading a captured serial stream.

    Raises ``ValueError`` naming the first bad byte and its offset, or a frame cut short.
    """
    data = bytes(data)
    frames: list[tuple[float, float]] = []
    for offset in range(0, len(data), FRAME_SIZE):
        if offset + FRAME_SIZE > len(data):
            raise ValueError(f"motor bytes: the frame at offset {offset} has {len(data) - offset} bytes, "
                             f"expected {FRAME_SIZE} (M1 opcode, speed, M2 opcode, speed)")
        speeds = {"M1": _motor_speed(data, offset, "M1", scale.max_speed),
                  "M2": _motor_speed(data, offset + 2, "M2", scale.max_speed)}
        left, right = speeds[scale.left_motor], speeds[scale.right_motor]
        frames.append((-left if scale.invert_left else left, -right if scale.invert_right else right))
    return frames


def open_serial_port(port: str, baud: int = DEFAULT_BAUD) -> serial.Serial:
    """The XBee's serial port, 8N1; a missing or busy port is a ``SerialEndpointError`` naming it."""
    try:
        return serial.Serial(port, baud, bytesize=serial.EIGHTBITS, parity=serial.PARITY_NONE,
                             stopbits=serial.STOPBITS_ONE, timeout=SIGNATURE_TIMEOUT, write_timeout=WRITE_TIMEOUT)
    except (serial.SerialException, OSError, ValueError) as error:
        raise SerialEndpointError(f"serial port {port}: cannot open it at {baud} baud: {error} "
                                  "(is the XBee plugged in and the device right? see ls /dev/serial/by-id/)") from None


def read_signature(link: serial.Serial, timeout: float = SIGNATURE_TIMEOUT) -> bytes:
    """Send the serial slave's signature query (0x81) and return what came back within ``timeout`` s.

    Empty when nothing answered; that is for the caller to report, not an error (see the module
    docstring). Stale input is discarded first so that only this answer is read.
    """
    link.reset_input_buffer()
    link.write(bytes((SEND_SIGNATURE,)))
    link.flush()
    previous, link.timeout = link.timeout, timeout
    try:
        return bytes(link.read(SIGNATURE_LENGTH))
    finally:
        link.timeout = previous


def describe_signature(answer: bytes, port: str, timeout: float = SIGNATURE_TIMEOUT) -> str:
    """One line on what the robot answered to 0x81, for the start-up log."""
    if not answer:
        return (f"no answer to the signature query (0x81) on {port} within {timeout:g} s: robot off, out of "
                "XBee range or not running the 3pi serial slave program (fine with a pseudo-terminal); going on")
    text = answer.decode("ascii", errors="replace")
    if len(answer) == SIGNATURE_LENGTH and answer.startswith(b"3pi"):
        return f"robot signature {text!r} on {port}"
    return (f"unexpected answer {answer!r} to the signature query (0x81) on {port}, expected 6 bytes like "
            "'3pi1.0': is the robot running the 3pi serial slave program? going on")


class SerialEndpoint:
    """One robot on Zenoh, driven through its serial port; ``run`` owns the port and the session.

    Zenoh calls ``_on_wheels`` and ``_on_host`` from its own threads while ``run``'s watchdog loops in
    the caller's thread; one lock guards the serial writes, the state and the counters, so a command
    and a watchdog stop never interleave their bytes.
    """

    def __init__(self, port: str, robot: int, prefix: str = DEFAULT_PREFIX, connect: Sequence[str] = (),
                 listen: Sequence[str] = (), zenoh_config_file: str | None = None, scale: SpeedScale = SpeedScale(),
                 command_timeout: float = DEFAULT_COMMAND_TIMEOUT, baud: int = DEFAULT_BAUD,
                 allow_insecure: bool = False, lab_key: LabKey | None = None) -> None:
        self.who = f"m3pi-serial robot {robot}"
        problems = check_prefix(prefix)
        if robot < 0:
            problems.append(f"robot id {robot} is negative")
        if not (math.isfinite(command_timeout) and command_timeout > 0):
            problems.append(f"command timeout {command_timeout} s, expected a finite time > 0")
        if problems:
            raise SerialEndpointError(f"{self.who}: " + "; ".join(problems))
        self.port = port
        self.robot = robot
        self.keys = RobotKeys(prefix, robot)
        self.connect = list(connect)
        self.listen = list(listen)
        self.zenoh_config_file = zenoh_config_file
        self.allow_insecure = allow_insecure
        self.scale = scale
        self.command_timeout = command_timeout
        self.baud = baud
        self.counters = LinkCounters()
        self.watchdog_stops = 0
        self._lock = threading.Lock()
        self._machine = StateMachine(self.who, self._announce)
        self._claim = RobotClaim(lab_key or load_lab_key(), self.keys.wheels)
        self._claim_changed = False  # a status is due at once
        self._link: serial.Serial | None = None
        self._command: WheelCommand | None = None  # the command the motors are running now
        self._last_valid = 0.0  # time.monotonic() of the last valid command
        self._fault: SerialEndpointError | None = None
        self._closing = False
        self._reported: set[Drop] = set()

    @property
    def state(self) -> LinkState:
        return self._machine.state

    def _say(self, text: str) -> None:
        print(f"{self.who}: {text}", file=sys.stderr, flush=True)

    def _announce(self, old: LinkState, new: LinkState, reason: str) -> None:
        self._say(f"{old.value} -> {new.value} ({reason})")

    # Everything below that writes or changes state runs with self._lock held.

    def _write(self, frame: bytes) -> None:
        """Write a frame; a failing port becomes the fault that ``run`` raises in its own thread."""
        if self._link is None:
            raise SerialEndpointError(f"{self.who}: serial port {self.port} is not open")
        try:
            self._link.write(frame)
        except (serial.SerialException, OSError) as error:
            self._fault = SerialEndpointError(f"{self.who}: writing to serial port {self.port} failed: {error}")
            raise self._fault from None

    def _stop_motors(self, reason: str) -> None:
        self._command = None
        try:
            self._write(STOP_FRAME)
        finally:
            self._machine.go(LinkState.STOPPED, reason)

    def _drop(self, error: MessageError) -> None:
        self.counters.drop(error)
        if error.reason not in self._reported:  # the first of each kind, then only counted (200 Hz streams)
            self._reported.add(error.reason)
            self._say(f"dropped {error} (first '{error.reason.value}' drop; later ones are counted)")

    def _on_wheels(self, sample: zenoh.Sample) -> None:
        """Zenoh callback: check one wheel command and, if valid, put it on the motors at once."""
        payload = sample.payload.to_bytes()
        arrival = time.time()
        with self._lock:
            if self._closing or self._fault is not None:
                return
            self._expire(arrival)
            owner = self._claim.owner
            try:
                command = self._claim.check(payload, arrival, f"robot {self.robot}")
            except MessageError as error:
                self._drop(error)
                return
            if self._claim.owner and self._claim.owner != owner:
                self._claimed(self._claim.owner, "claim request")
            elif owner and not self._claim.owner:
                self._ended(owner, "its run released it")
            if command is None:
                return
            self.counters.accept()
            stop = command.left == 0.0 and command.right == 0.0
            try:
                self._write(motor_bytes(command.left, command.right, self.scale))
            except SerialEndpointError:
                return  # run() raises the fault in its thread
            self._claim.record_applied(command.seq)
            self._last_valid = time.monotonic()
            if stop:  # always applied, whatever its number (bridge.claim)
                self._command = None
                if self._machine.state is LinkState.RUNNING:
                    self._machine.go(LinkState.STOPPED, f"stop command {command.seq}")
                return
            self._command = command
            self._machine.go(LinkState.RUNNING, f"valid command {command.seq}")

    def _on_host(self, sample: zenoh.Sample) -> None:
        """Zenoh callback on the hosts' claim tokens: the first one claims the robot; the owner's going means
        stop now, not at the deadline."""
        claim = claim_from_key(str(sample.key_expr))
        if claim is None:
            return
        with self._lock:
            if self._closing or self._fault is not None:
                return
            self._expire(time.time())
            if sample.kind == zenoh.SampleKind.PUT:
                if self._claim.host_appeared(claim, time.time()):
                    self._claimed(claim, str(sample.key_expr))
                elif self._claim.owner and claim != self._claim.owner:
                    self._say(f"host of claim {claim_text(claim)} appeared while claim "
                              f"{claim_text(self._claim.owner)} holds the robot; its commands are refused")
            elif self._claim.host_left(claim):
                self._ended(claim, f"its token {sample.key_expr} went")

    def _expire(self, now: float) -> None:
        """End the claim if its run stopped renewing it (``bridge.claim``: killed, frozen, cut off)."""
        ended = self._claim.expire(now)
        if ended:
            self._ended(ended, f"its lease of {self._claim.lease:g} s ran out")

    def _ended(self, claim: int, how: str) -> None:
        """The claim ended: the motors stop at once (a failing port becomes the fault ``run`` raises)."""
        self._claim_changed = True
        self._say(f"claim {claim_text(claim)} released ({how})")
        try:
            self._stop_motors(f"claim ended: {how}")
        except SerialEndpointError:
            return

    def _claimed(self, claim: int, how: str) -> None:
        self._claim_changed = True
        self._say(f"claimed by {claim_text(claim)} ({how})")
        if self._machine.state is LinkState.CONFIGURED:
            self._machine.go(LinkState.SYNCHRONIZED, "host present")

    def _watch_once(self) -> None:
        """Stop the motors if the running command expired or commands stopped coming."""
        if self._machine.state is not LinkState.RUNNING or self._command is None:
            return
        if time.time() >= self._command.deadline:
            reason = f"command deadline passed, seq {self._command.seq}"
        elif time.monotonic() - self._last_valid >= self.command_timeout:
            reason = f"no valid command for {self.command_timeout:g} s"
        else:
            return
        self.watchdog_stops += 1
        self._stop_motors(reason)

    def _watch(self, stop_event: threading.Event, session: zenoh.Session) -> None:
        """The watchdog, and the status (claim and counts) every ``STATUS_PERIOD`` or at once after a claim change."""
        status_seq, reported = 0, 0.0
        with session.declare_publisher(self.keys.status, express=True) as publisher:
            while not stop_event.is_set():
                now = time.time()
                with self._lock:
                    if self._fault is not None:
                        raise self._fault
                    self._watch_once()
                    self._expire(now)
                    due = self._claim_changed or now - reported >= STATUS_PERIOD
                    said = self._claim.statuses(status_seq + 1, now) if due else []
                    if due:
                        status_seq += len(said)
                        self._claim_changed, reported = False, now
                for status in said:
                    publisher.put(encode_status(status))
                stop_event.wait(WATCHDOG_PERIOD)

    def _shutdown(self, reason: str, failed: bool) -> SerialEndpointError | None:
        """Zero the motors (always, whatever the state) before the port closes; print the counters."""
        problem: SerialEndpointError | None = None
        with self._lock:
            self._closing = True
            if failed and self._machine.state is not LinkState.ERROR:
                self._machine.go(LinkState.ERROR, reason)
            try:
                self._write(STOP_FRAME)
                assert self._link is not None
                self._link.flush()
            except (SerialEndpointError, serial.SerialException, OSError) as error:
                problem = SerialEndpointError(f"{self.who}: could not zero the motors on exit ({error}): the robot "
                                              "may still be moving, switch it off")
                self._say(str(problem))
            self._command = None
            self._machine.go(LinkState.STOPPED, "exit" if failed else reason)
        self._say(self.summary())
        return problem

    def summary(self) -> str:
        """The counters in one line (printed at exit)."""
        c = self.counters
        drops = c.drop_reasons() or "none"
        line = (f"wheel commands received {c.received}, accepted {c.accepted}, dropped {c.dropped_total} ({drops}); "
                f"watchdog stops {self.watchdog_stops}")
        return line + (f"; last problem: {c.last_problem}" if c.last_problem else "")

    def run(self, stop_event: threading.Event | None = None) -> LinkCounters:
        """Serve the robot until ``stop_event`` is set, ``KeyboardInterrupt`` or an error; return the counters.

        The port opens first (a missing one fails before any network set-up) and closes last, so the
        motors are zeroed at start-up and on every way out.
        """
        stop_event = stop_event if stop_event is not None else threading.Event()
        with open_serial_port(self.port, self.baud) as link:
            self._link = link
            reason, failed = "stop requested", False
            try:
                self._say(describe_signature(read_signature(link), self.port))
                with self._lock:
                    self._write(STOP_FRAME)
                config = zenoh_config(self.connect, self.listen, self.zenoh_config_file,
                                      allow_insecure=self.allow_insecure)
                # Subscribers before the token: a host that sees the token may command at once.
                with (open_session(config, self.who) as session,
                      session.declare_subscriber(self.keys.wheels, self._on_wheels),
                      session.liveliness().declare_subscriber(self.keys.hosts, self._on_host, history=True),
                      session.liveliness().declare_token(self.keys.alive)):
                    self._say(f"serving {self.keys.wheels} on {self.port} at {self.baud} baud "
                              f"(max speed {self.scale.max_speed:g} m/s = byte {SPEED_BYTE_MAX}, "
                              f"left {self.scale.left_motor}, right {self.scale.right_motor})")
                    self._watch(stop_event, session)
            except KeyboardInterrupt:
                reason = "interrupted"
                raise
            except BaseException as error:
                reason, failed = f"{type(error).__name__}: {error}", True
                raise
            finally:
                problem = self._shutdown(reason, failed)
                self._link = None
            if problem is not None:
                raise problem
        return self.counters


def run_serial_endpoint(port: str, robot: int, prefix: str = DEFAULT_PREFIX, connect: Sequence[str] = (),
                        listen: Sequence[str] = (), zenoh_config_file: str | None = None,
                        scale: SpeedScale = SpeedScale(), command_timeout: float = DEFAULT_COMMAND_TIMEOUT,
                        baud: int = DEFAULT_BAUD, stop_event: threading.Event | None = None,
                        allow_insecure: bool = False, lab_key: LabKey | None = None) -> LinkCounters:
    """Stand for robot ``robot`` on Zenoh and drive it through serial ``port`` (``platoon m3pi-serial``).

    Blocks until ``stop_event`` is set or ``KeyboardInterrupt`` (the CLI turns SIGINT/SIGTERM into
    it); returns the wheel-command counters. Raises ``SerialEndpointError`` (port, write, settings)
    or ``bridge.session.SessionError`` (Zenoh), with the motors zeroed first whenever the port opened.
    """
    endpoint = SerialEndpoint(port, robot, prefix=prefix, connect=connect, listen=listen,
                              zenoh_config_file=zenoh_config_file, scale=scale, command_timeout=command_timeout,
                              baud=baud, allow_insecure=allow_insecure, lab_key=lab_key)
    return endpoint.run(stop_event)
