"""The m3pi link's wire protocol: Zenoh keys, message layouts, and the checks every message passes.

Keys (one namespace per run and robot, slash-separated so that zenoh-bridge-ros2dds maps key
``a/b/c`` to the ROS 2 topic ``/a/b/c``):

* ``<prefix>/m3pi/<id>/pose``          pose of robot ``id``, from the motion capture (or the emulator)
* ``<prefix>/m3pi/<id>/cmd/wheels``    wheel speed command to robot ``id``, from the host
* ``<prefix>/m3pi/<id>/status``        the robot side's claim and command counts, 20 times a second
* ``<prefix>/m3pi/<id>/alive``         liveliness token of the robot side (emulator, serial endpoint)
* ``<prefix>/m3pi/<id>/host/<claim>``  liveliness token of a host that claims the robot: ``claim`` is
                                       the run's random 64-bit claim id, 16 hex digits (``bridge.claim``)

Payloads are fixed-size little-endian structs, version byte first (docs/hil.md has the tables).
Version 2 added the claim id to every pose and command and the status message; version 3 the MAC of
every wheel command (``bridge.lab_key``), claim requests and the status's released claim; version 4 the
claim's lease (the run renews it; the robot side ends a claim not renewed for ``bridge.claim.CLAIM_LEASE``)
and the run's MAC'd release. A peer of another version's messages are dropped as ``version`` and named as
such, never misread:

* pose, 52 bytes: version u8, kind u8 = 1, flags u16 = 0, seq u32, command_seq u32 (the last wheel
  command the robot had applied when the pose was taken; 0 = none), claim u64 (the claim that command
  belonged to; 0 = unknown, e.g. a motion capture), stamp f64 (s, the pose's own Unix time), x f64
  (m), y f64 (m), heading f64 (rad, counter-clockwise from x)
* wheels, 56 bytes: version u8, kind u8 = 2, flags u16 (bit 0: the release of the claim, numbered 0,
  both speeds 0), seq u32 (from 1 per claim; 0 = a claim
  request, both speeds 0), claim u64, deadline f64 (Unix time after which the robot stops by itself),
  left f64 (m/s), right f64 (m/s), then mac 16 bytes (HMAC-SHA256 with the lab key over the command key
  and the 40 bytes before it, ``bridge.lab_key``)
* status, 60 bytes: version u8, kind u8 = 3, flags u16 (bit 0: this robot side publishes the poses,
  so they echo the claim; bit 1: the released claim ended because its lease ran out; bits 4-7: why the
  last refused message was refused, ``REFUSALS``), seq u32, owner u64 (the claim it obeys; 0 = none), applied u32, accepted
  u32, dropped u32 (the owner's commands: last applied, accepted, dropped as late, duplicate ...),
  foreign u32 (well-formed commands of another claim or without a valid MAC, refused), invalid u32
  (undecodable commands), foreign_claim u64 (the claim of the last refused one), released u64 (the claim
  that ended last, while none holds the robot: its counts are the ones above), stamp f64

A receiver checks size, version, kind, flags, finite numbers, then the sequence number (a duplicate or
an older number is dropped; a sender numbers its messages from 1) and the time stamp (a pose too old,
or a command whose deadline has passed: late). Every drop has a ``Drop`` reason, and
receivers count them by reason (``LinkCounters``): nothing malformed ever reaches the guidance or
the motors, and nothing is dropped silently.
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass, field
from enum import Enum
from struct import Struct
from typing import Any

VERSION = 4
DEFAULT_PREFIX = "platoon"
MAX_PAYLOAD = 256  # bytes: anything larger is "oversized" and not even looked at

_POSE = Struct("<BBHIIQdddd")
_WHEELS = Struct("<BBHIQddd")
_STATUS = Struct("<BBHIQIIIIIQQd")
MAC_SIZE = 16  # bytes of HMAC-SHA256 after a wheel command's fields (bridge.lab_key)
POSE_KIND, WHEELS_KIND, STATUS_KIND = 1, 2, 3
POSE_SIZE, WHEELS_BODY, STATUS_SIZE = _POSE.size, _WHEELS.size, _STATUS.size
WHEELS_SIZE = WHEELS_BODY + MAC_SIZE
_LAYOUTS = {POSE_KIND: _POSE, WHEELS_KIND: _WHEELS, STATUS_KIND: _STATUS}
STATUS_POSES = 0x1  # status flag: this robot side publishes the robot's poses (they echo the claim)
STATUS_LEASE_ENDED = 0x2  # status flag: the released claim ended because its run stopped renewing it (bridge.claim)
REFUSAL_SHIFT = 4  # status flags bits 4-7: why the robot side refused the last refused message (foreign_claim's)
WHEELS_RELEASE = 0x1  # wheel command flag: the run releases its claim (a MAC'd release: a copied token ends nothing)
MAX_COMMAND_AHEAD = 6.0  # s: a command whose deadline is further ahead is refused (config: validity <= 5 s)

_PREFIX_SEGMENT = re.compile(r"^[A-Za-z0-9_.-]+$")


class Drop(Enum):
    """Why a received message was not used (the counters and the trace use ``.value``)."""

    OVERSIZED = "oversized"
    MALFORMED = "malformed"  # wrong length, kind or flags
    VERSION = "version"  # another protocol version
    NON_FINITE = "non_finite"
    DUPLICATE = "duplicate"  # the sequence number seen last, again
    OUT_OF_ORDER = "out_of_order"  # older than the newest seen
    LATE = "late"  # pose too old, or a command whose deadline has passed
    FUTURE = "future"  # stamped ahead of the receiver's clock (clocks not synchronized?), or a deadline too far
    FOREIGN = "foreign"  # not of this claim: another run's or a stranger's
    UNAUTHENTICATED = "unauthenticated"  # a wheel command whose MAC does not check with the lab key


# the codes of those bits: 0 none; what the run tells its user from them (the robot side's view, not a guess)
REFUSALS: tuple[Drop | None, ...] = (None, Drop.UNAUTHENTICATED, Drop.FOREIGN, Drop.LATE, Drop.FUTURE)
STATUS_FLAGS = STATUS_POSES | STATUS_LEASE_ENDED | (0xF << REFUSAL_SHIFT)


class MessageError(ValueError):
    """A message that must be dropped: ``reason`` for the counters, the text says what was wrong."""

    def __init__(self, reason: Drop, problem: str) -> None:
        super().__init__(problem)
        self.reason = reason


@dataclass(frozen=True)
class Pose:
    seq: int
    command_seq: int
    stamp: float
    x: float
    y: float
    heading: float
    claim: int = 0  # the claim of command ``command_seq``; 0 = unknown (a motion capture knows no claims)


@dataclass(frozen=True)
class WheelCommand:
    seq: int
    deadline: float
    left: float
    right: float
    claim: int = 0
    release: bool = False  # the run releases its claim (numbered 0, both speeds 0)


@dataclass(frozen=True)
class Status:
    """What a robot side reports about its claim and the commands it received (``bridge.claim``)."""

    seq: int
    owner: int  # the claim it obeys, 0 = none
    applied: int  # the owner's last applied command
    accepted: int  # the owner's commands accepted
    dropped: int  # the owner's commands dropped (late, duplicate, out of order, deadline too far)
    foreign: int  # well-formed commands of another claim, refused
    invalid: int  # commands that did not decode (malformed, another version ...)
    foreign_claim: int  # the claim of the last foreign command, 0 = none
    stamp: float
    flags: int = 0
    released: int = 0  # with owner 0: the claim that ended last (the counts above are still its own)

    @property
    def refusal(self) -> Drop | None:
        """Why the robot side refused the last refused message (that of ``foreign_claim``), if it says."""
        return REFUSALS[(self.flags >> REFUSAL_SHIFT) & 0xF]


def refusal_flags(reason: Drop | None) -> int:
    """The status flags that say ``reason`` (a refusal of another kind says none)."""
    return (REFUSALS.index(reason) if reason in REFUSALS else 0) << REFUSAL_SHIFT


def check_prefix(prefix: str) -> list[str]:
    """Problems with a key prefix (empty list: usable). Segments of letters, digits, ``_ . -``."""
    if not prefix:
        return ["the prefix is empty"]
    bad = [segment for segment in prefix.split("/") if not _PREFIX_SEGMENT.match(segment)]
    if bad:
        return [f"prefix {prefix!r}: segment {bad[0]!r} is not letters, digits, '_', '.' or '-' (no wildcards, "
                "no empty segments)"]
    return []


@dataclass(frozen=True)
class RobotKeys:
    """Every key of one robot, built in one place."""

    prefix: str
    robot: int

    def _key(self, tail: str) -> str:
        return f"{self.prefix}/m3pi/{self.robot}/{tail}"

    @property
    def pose(self) -> str:
        return self._key("pose")

    @property
    def wheels(self) -> str:
        return self._key("cmd/wheels")

    @property
    def alive(self) -> str:
        return self._key("alive")

    @property
    def status(self) -> str:
        return self._key("status")

    @property
    def hosts(self) -> str:
        """Every host's claim token (a liveliness key expression)."""
        return self._key("host/*")

    def host(self, claim: int) -> str:
        """The liveliness token of the host holding claim ``claim``."""
        return self._key(f"host/{claim:016x}")


def encode_pose(pose: Pose) -> bytes:
    return _POSE.pack(VERSION, POSE_KIND, 0, pose.seq, pose.command_seq, pose.claim, pose.stamp, pose.x, pose.y,
                      pose.heading)


def encode_wheels(command: WheelCommand, key: Any = None, key_expr: str = "") -> bytes:
    """The command's bytes, with the MAC the lab key ``key`` (a ``bridge.lab_key.LabKey``) makes for the
    command key ``key_expr``; without a key the MAC is zeros (a stranger's, refused by every robot side)."""
    flags = WHEELS_RELEASE if command.release else 0
    body = _WHEELS.pack(VERSION, WHEELS_KIND, flags, command.seq, command.claim, command.deadline, command.left,
                        command.right)
    return body + (key.mac(key_expr, body) if key is not None else bytes(MAC_SIZE))


def encode_status(status: Status) -> bytes:
    return _STATUS.pack(VERSION, STATUS_KIND, status.flags, status.seq, status.owner, status.applied, status.accepted,
                        status.dropped, status.foreign, status.invalid, status.foreign_claim, status.released,
                        status.stamp)


def _header(payload: bytes, kind: int, size: int, what: str, flags: int = 0) -> tuple:
    if len(payload) > MAX_PAYLOAD:
        raise MessageError(Drop.OVERSIZED, f"{what}: {len(payload)} bytes, more than {MAX_PAYLOAD}")
    # another version only if the rest of the header looks like ours (a known kind, no flags); any other
    # first byte is plain garbage
    if len(payload) >= 4 and payload[0] != VERSION and payload[1] in _LAYOUTS and payload[2:4] == b"\0\0":
        raise MessageError(Drop.VERSION, f"{what}: protocol version {payload[0]}, expected {VERSION} (the peer runs "
                                         "another release of platoon-cosim: update both sides)")
    if len(payload) >= 1 and payload[0] != VERSION:
        raise MessageError(Drop.MALFORMED, f"{what}: not a version-{VERSION} message (first byte {payload[0]:#04x})")
    if len(payload) != size:
        raise MessageError(Drop.MALFORMED, f"{what}: {len(payload)} bytes, expected {size}")
    fields = _LAYOUTS[kind].unpack(payload[:_LAYOUTS[kind].size])  # a wheel command's MAC follows its fields
    if fields[1] != kind:
        raise MessageError(Drop.MALFORMED, f"{what}: message kind {fields[1]}, expected {kind}")
    if fields[2] & ~flags:
        raise MessageError(Drop.MALFORMED, f"{what}: flags {fields[2]:#x}, expected {flags:#x} at most")
    return fields


def _finite(what: str, names: tuple[str, ...], values: tuple[float, ...]) -> None:
    bad = [f"{name} = {value}" for name, value in zip(names, values) if not math.isfinite(value)]
    if bad:
        raise MessageError(Drop.NON_FINITE, f"{what}: {', '.join(bad)} (not finite)")


def decode_pose(payload: bytes) -> Pose:
    """A pose from its bytes, or ``MessageError`` saying why not (size, version, kind, finite)."""
    _, _, _, seq, command_seq, claim, stamp, x, y, heading = _header(bytes(payload), POSE_KIND, POSE_SIZE, "pose")
    _finite("pose", ("stamp", "x", "y", "heading"), (stamp, x, y, heading))
    return Pose(seq, command_seq, stamp, x, y, heading, claim)


def decode_wheels(payload: bytes) -> WheelCommand:
    """A wheel command from its bytes, or ``MessageError`` saying why not."""
    _, _, flags, seq, claim, deadline, left, right = _header(bytes(payload), WHEELS_KIND, WHEELS_SIZE, "wheel command",
                                                             WHEELS_RELEASE)
    _finite("wheel command", ("deadline", "left", "right"), (deadline, left, right))
    release = bool(flags & WHEELS_RELEASE)
    if release and (seq != 0 or left != 0.0 or right != 0.0):
        raise MessageError(Drop.MALFORMED, f"wheel command {seq}: a release (flag bit 0) numbered {seq} or with speeds "
                                           "(a release is numbered 0, both speeds 0)")
    return WheelCommand(seq, deadline, left, right, claim, release)


def decode_status(payload: bytes) -> Status:
    """A robot side's status from its bytes, or ``MessageError`` saying why not."""
    _, _, flags, *numbers, released, stamp = _header(bytes(payload), STATUS_KIND, STATUS_SIZE, "status", STATUS_FLAGS)
    _finite("status", ("stamp",), (stamp,))
    if (flags >> REFUSAL_SHIFT) & 0xF >= len(REFUSALS):
        raise MessageError(Drop.MALFORMED, f"status: refusal code {(flags >> REFUSAL_SHIFT) & 0xF} in its flags, "
                                           f"expected at most {len(REFUSALS) - 1}")
    return Status(*numbers, stamp=stamp, flags=flags, released=released)


class SequenceCheck:
    """Accepts strictly increasing sequence numbers; names the reason for any other."""

    def __init__(self) -> None:
        self.last = 0

    def check(self, seq: int, what: str) -> None:
        if seq == self.last:
            raise MessageError(Drop.DUPLICATE, f"{what}: sequence number {seq} again")
        if seq < self.last:
            raise MessageError(Drop.OUT_OF_ORDER, f"{what}: sequence number {seq} after {self.last}")
        self.last = seq


def check_pose_time(pose: Pose, now: float, max_age: float, max_ahead: float = 0.05) -> None:
    """A pose's stamp must be at most ``max_age`` s old and at most ``max_ahead`` s in the future."""
    age = now - pose.stamp
    if age > max_age:
        raise MessageError(Drop.LATE, f"pose {pose.seq}: {age * 1e3:.1f} ms old, more than {max_age * 1e3:.0f} ms")
    if age < -max_ahead:
        raise MessageError(Drop.FUTURE, f"pose {pose.seq}: stamped {-age * 1e3:.1f} ms ahead of this clock "
                                        "(are the clocks synchronized?)")


def check_command_deadline(command: WheelCommand, now: float) -> None:
    """A command whose deadline has passed on arrival is never applied, nor one that would hold the wheels
    for longer than any run asks (``MAX_COMMAND_AHEAD``: a forged one must not outlive its sender's claim)."""
    if command.deadline <= now:
        raise MessageError(Drop.LATE, f"wheel command {command.seq}: deadline passed "
                                      f"{(now - command.deadline) * 1e3:.1f} ms before it arrived")
    if command.deadline > now + MAX_COMMAND_AHEAD:
        raise MessageError(Drop.FUTURE, f"wheel command {command.seq}: deadline {command.deadline - now:.1f} s ahead, "
                                        f"more than {MAX_COMMAND_AHEAD:g} s (are the clocks synchronized?)")


@dataclass
class LinkCounters:
    """Messages received on one stream, how many were used, and the drops by reason."""

    received: int = 0
    accepted: int = 0
    dropped: dict[str, int] = field(default_factory=lambda: {reason.value: 0 for reason in Drop})
    last_problem: str = ""

    def accept(self) -> None:
        self.received += 1
        self.accepted += 1

    def drop(self, error: MessageError) -> None:
        self.received += 1
        self.dropped[error.reason.value] += 1
        self.last_problem = str(error)

    @property
    def dropped_total(self) -> int:
        return sum(self.dropped.values())

    def drop_reasons(self) -> str:
        """The drops by reason, those that happened: "late 3, duplicate 1" ("" if none)."""
        return ", ".join(f"{reason} {count}" for reason, count in self.dropped.items() if count)

    def as_dict(self, stream: str) -> dict[str, float]:
        """Flat numbers, e.g. ``pose.received``, ``pose.dropped.late``, for the trace and summaries."""
        values: dict[str, float] = {f"{stream}.received": self.received, f"{stream}.accepted": self.accepted}
        values.update({f"{stream}.dropped.{reason}": count for reason, count in self.dropped.items()})
        return values
