"""Who drives a robot: one run at a time, by claim, and each side checks the other.

A run claims a robot with a fresh random 64-bit claim id: it declares the liveliness token
``<prefix>/m3pi/<id>/host/<claim>`` and puts that claim in every wheel command. The robot side
(emulator, ``m3pi-serial``) obeys the first claim it sees while it obeys none, numbers that claim's
commands afresh (so nothing sent before, a sequence number 2^32 - 1 included, touches the next run),
and refuses every command of any other claim: counted, and reported back on its status key. The claim
ends when its token goes: the run released it (it undeclares the token after its stop commands) or
its session died (Zenoh drops the token). Nothing else ends it, so another run's or a stranger's
token or command can never take a robot that is claimed.

``RobotClaim`` is the robot side's bookkeeping, ``HostClaim`` the run's: it tells its own poses from
foreign ones (another publisher on the pose key: dropped and counted as ``foreign``, with their own
sequence numbers, so they never lock out the robot's), and it notices when the robot does not do
what the run commands: a pose or status echoing a command the run never sent (someone drives with
this run's claim), or most of the run's commands refused.

Without authentication anyone who can read the traffic can copy a claim id; that is what TLS and
access control are for (docs/hil.md, "Threat model"). The claim stops everything short of that:
stale or replayed commands, a second run, a script left running, garbage, poses from elsewhere.
"""

from __future__ import annotations

import secrets
from dataclasses import dataclass, field

from .protocol import (
    STATUS_POSES,
    Drop,
    MessageError,
    Pose,
    SequenceCheck,
    Status,
    WheelCommand,
    check_command_deadline,
    decode_wheels,
)

REFUSED_VERDICT_AFTER = 50  # commands the robot side received before "mostly refused" can end a run
GRANT_GRACE = 1.0  # s the robot side may take to see a new claim before its status naming another owner counts


def new_claim() -> int:
    """A fresh random claim id, never 0 (0 means "no claim" on the wire)."""
    return secrets.randbits(64) or 1


def claim_text(claim: int) -> str:
    return f"{claim:016x}"


def claim_from_key(key: str) -> int | None:
    """The claim of a host token ``.../host/<16 hex digits>``, or None for any other key."""
    tail = key.rsplit("/", 1)[-1]
    if len(tail) != 16:
        return None
    try:
        return int(tail, 16) or None
    except ValueError:
        return None


@dataclass
class RobotClaim:
    """The robot side's claim: whom it obeys, and the counts it reports on its status key."""

    owner: int = 0
    hosts: set[int] = field(default_factory=set)  # claims whose tokens are present
    sequence: SequenceCheck = field(default_factory=SequenceCheck)
    applied: int = 0
    accepted: int = 0
    dropped: int = 0
    foreign: int = 0
    invalid: int = 0
    foreign_claim: int = 0
    released: int = 0  # the claim that ended last: its stragglers are late, not foreign

    def host_appeared(self, claim: int) -> bool:
        """A host's token appeared; True if that claim is now the owner (the robot was free)."""
        self.hosts.add(claim)
        if self.owner:
            return False
        self.owner = claim
        self.sequence = SequenceCheck()
        self.applied = self.accepted = self.dropped = self.foreign = self.invalid = self.foreign_claim = 0  # per claim
        return True

    def host_left(self, claim: int) -> bool:
        """A host's token went; True if it was the owner's (the claim ended: stop the wheels)."""
        self.hosts.discard(claim)
        if claim != self.owner:
            return False
        self.owner, self.released = 0, claim
        return True

    def check(self, payload: bytes, now: float, what: str) -> WheelCommand:
        """The command in ``payload`` if the owner sent it in order and in time, else ``MessageError``
        (counted here: ``invalid``, ``foreign`` or the owner's ``dropped``)."""
        try:
            command = decode_wheels(payload)
        except MessageError:
            self.invalid += 1
            raise
        if command.claim == self.released and not self.owner:  # its last stop, overtaken by the token's going
            raise MessageError(Drop.LATE, f"wheel command {command.seq} of claim {claim_text(command.claim)}: "
                                          "arrived after its claim ended")
        if not self.owner or command.claim != self.owner:
            self.foreign += 1
            self.foreign_claim = command.claim
            holder = f"claim {claim_text(self.owner)}" if self.owner else "no claim"
            raise MessageError(Drop.FOREIGN, f"wheel command {command.seq} of claim {claim_text(command.claim)}: "
                                             f"{what} obeys {holder}; refused")
        try:
            self.sequence.check(command.seq, f"wheel command {command.seq}")
            check_command_deadline(command, now)
        except MessageError:
            self.dropped += 1
            raise
        self.accepted += 1
        return command

    def status(self, seq: int, now: float, flags: int = 0) -> Status:
        return Status(seq, self.owner, self.applied, self.accepted, self.dropped, self.foreign, self.invalid,
                      self.foreign_claim, now, flags)


class NotDriving(Exception):
    """The robot does not do what this run commands; the text says why and who."""


@dataclass
class HostClaim:
    """The run's side of its claim: which poses are its robot's, and whether the robot obeys it."""

    claim: int = field(default_factory=new_claim)
    echoes: bool = False  # the pose source echoes claims (an emulator): claim-0 poses are someone else's
    granted: bool = False  # the robot side said (status) or showed (a pose) that it obeys this claim
    status: Status | None = None  # the newest status naming this claim
    other_owner: int = 0  # the owner the newest status named, when not this claim
    foreign_poses: int = 0
    _sequences: dict[int, SequenceCheck] = field(default_factory=dict)

    def source(self, pose: Pose) -> None:
        """``MessageError`` (foreign) unless the pose is this run's robot's: it echoes this claim, or it
        carries none and the pose source is one that never does (a motion capture)."""
        if pose.claim != self.claim and (pose.claim != 0 or self.echoes):
            self.foreign_poses += 1
            raise MessageError(Drop.FOREIGN, f"pose {pose.seq} of claim {claim_text(pose.claim)}, not this run's "
                                             f"{claim_text(self.claim)}: another publisher on the pose key")

    def accept(self, pose: Pose, sent: int) -> None:
        """After ``source`` and the time check: the sequence check of the pose's own source (so a foreign
        stream never locks out the robot's), then ``NotDriving`` if the robot applied a command this run
        never sent (``sent``: the newest command it sent)."""
        self._sequences.setdefault(pose.claim, SequenceCheck()).check(pose.seq, f"pose {pose.seq}")
        if pose.claim == self.claim:
            self.echoes = self.granted = True
            if pose.command_seq > sent:
                raise NotDriving(f"the robot applied command {pose.command_seq} of this run's claim "
                                 f"{claim_text(self.claim)}, but the run sent only {sent}: someone else drives it with "
                                 "this run's claim")

    def robot_status(self, status: Status, sent: int) -> None:
        """Take a robot side's status: ``NotDriving`` if it obeyed or refused what it must not."""
        if status.owner != self.claim:
            self.other_owner = status.owner
            return
        self.granted, self.status, self.other_owner = True, status, 0
        if status.flags & STATUS_POSES:  # only the claimed robot side says how to tell its poses
            self.echoes = True
        if status.applied > sent:
            raise NotDriving(f"the robot side applied command {status.applied} of this run's claim, but the run sent "
                             f"only {sent}: someone else drives it with this run's claim")
        received = status.accepted + status.dropped
        if received >= REFUSED_VERDICT_AFTER and status.dropped > status.accepted:
            raise NotDriving(f"the robot side refused most of this run's commands: accepted {status.accepted}, dropped "
                             f"{status.dropped} of {received} received (late, duplicate or out of order: see its log)")

    def interference(self) -> str:
        """Who else tried to drive the robot, as the robot side reported it ("" if nobody)."""
        status = self.status
        if status is None:
            return ""
        return describe_interference(status.foreign, status.invalid, claim_text(status.foreign_claim))


def describe_interference(foreign: int, invalid: int, foreign_claim: str) -> str:
    """The robot side's refusals in words (also for the run's summary table, from the link statistics)."""
    parts = []
    if foreign:
        parts.append(f"{foreign} commands of other claims (the last of claim {foreign_claim})")
    if invalid:
        parts.append(f"{invalid} invalid commands")
    return "the robot side refused " + " and ".join(parts) if parts else ""
