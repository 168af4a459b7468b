"""Who drives a robot: one run at a time, by claim, and each side checks the other.

A run claims a robot with a fresh random 64-bit claim id: it declares the liveliness token
``<prefix>/m3pi/<id>/host/<claim>``, sends claim requests (commands numbered 0) until the robot side
grants it, and puts that claim in every wheel command. Every request and command carries a MAC made
with the lab key (``bridge.lab_key``): the robot side (emulator, ``m3pi-serial``) grants the first
claim whose token is there and whose request checks with its own key, while it obeys none; it numbers
that claim's commands afresh (so nothing sent before, a sequence number 2^32 - 1 included, touches the
next run), and refuses every command of any other claim or without a valid MAC: counted, and reported
back on its status key. The claim ends on what only its run can say, or on its run's silence:

* the run's release: a MAC'd message (flag bit 0, numbered 0), sent after its stop commands;
* its lease: every fresh authenticated message of the run renews it (a command in sequence, a claim
  request in time; the run renews every ``LEASE_RENEW_PERIOD`` from its grant to its release), and the
  robot side ends the claim ``CLAIM_LEASE`` after the last renewal (a run killed, frozen or cut off);
* its token's going (the run's session died: Zenoh drops the token) ends it at once.

A copy of the run's token held by someone without the key therefore holds nothing: the release or
the lease ends the claim anyway (a replayed claim request renews it for at most its own validity). An
ended claim is never granted again. Without a lab key (commands on a ROS topic carry no MAC) there is
no lease: the token alone says who holds the robot.

``RobotClaim`` is the robot side's bookkeeping, ``HostClaim`` the run's: it tells its own poses from
foreign ones (another publisher on the pose key: dropped and counted as ``foreign``, with their own
sequence numbers, so they never lock out the robot's), and it notices when the robot does not do
what the run commands: a pose or status echoing a command the run never sent (someone drives with
this run's claim, up to and including the status that says the claim ended), or most of the run's
commands refused.

Who holds no lab key cannot claim, command or hold a robot, even when it reads the traffic (it can
copy a claim id, not make a MAC); TLS and access control keep the traffic itself from strangers
(docs/hil.md, "Threat model").
"""
from __future__ import annotations

import secrets
from collections import deque
from dataclasses import dataclass, field, replace

import threading
from typing import Callable

from .lab_key import LabKey
from .protocol import (
    STATUS_LEASE_ENDED,
    STATUS_POSES,
    WHEELS_BODY,
    Drop,
    MessageError,
    Pose,
    SequenceCheck,
    Status,
    WheelCommand,
    MAX_COMMAND_AHEAD,
    check_command_deadline,
    decode_wheels,
    refusal_flags,
)

REFUSED_VERDICT_AFTER = 50  # commands the robot side received before "mostly refused" can end a run
ENDED_KEPT = 1024  # claims that ended, remembered so that a copy of their requests never claims the robot again
GRANT_GRACE = 1.0  # s the robot side may take to see a new claim before its status naming another owner counts
# s a claim holds without a renewal: a run renews it 8 times as often, so a stalled machine (a second or so
# without scheduling the run) does not lose it; the next run after a killed one drives within this (plus its start)
CLAIM_LEASE = 2.0
LEASE_RENEW_PERIOD = 0.25  # s between a run's renewals (claim requests of its granted claim)
CLAIM_REQUEST_VALIDITY = 1.0  # s a claim request stays valid (its deadline): a replay renews a lease for at most this


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
    """The robot side's claim: whom it obeys, and the counts it reports on its status key.

    With a lab key (our wheel protocol) a claim is granted only to a run that proves it holds the key:
    a claim request (a command numbered 0, both speeds 0) with a valid MAC, while that claim's token is
    there. A token alone claims nothing, so a stranger who reaches the robot side but holds no key never
    moves nor blocks the robot. Without a key (commands on a ROS topic, which carry no claim: Zenoh's
    access control guards them) the first token claims the robot, as the claim only numbers commands then.

    A stop (both speeds 0) of the claim is applied whatever its number and however late, also right after
    its claim ended: stopping is always safe, and a copied command numbered 2^31 must not lock out the
    run's stops. ``applied`` is the highest number applied, so the run sees a command it never sent
    even when its own stops came after it."""

    key: LabKey | None = None
    command_key: str = ""  # the key expression the commands' MACs name
    owner: int = 0
    hosts: set[int] = field(default_factory=set)  # claims whose tokens are present
    sequence: SequenceCheck = field(default_factory=SequenceCheck)
    applied: int = 0
    accepted: int = 0
    dropped: int = 0
    foreign: int = 0
    invalid: int = 0
    foreign_claim: int = 0
    foreign_reason: Drop | None = None  # why the last refused message (foreign_claim's) was refused
    released: int = 0  # the claim that ended last: its stragglers are late, not foreign
    ended: deque = field(default_factory=lambda: deque(maxlen=ENDED_KEPT))  # never granted again
    requests: dict[int, float] = field(default_factory=dict)  # claim -> deadline of a valid request before its token
    lease: float = CLAIM_LEASE  # s the owner's claim holds without a renewal (with a lab key)
    renewed: float = 0.0  # when the owner last renewed its claim
    lease_ended: bool = False  # the released claim ended because its lease ran out (a status flag)
    # the status that says the last claim ended, until a status said it: a waiting claim can be granted in the same
    # breath (its request arrives as the lease runs out), and the ended claim's run, or a bystander, must still hear
    unsaid_end: Status | None = None

    def host_appeared(self, claim: int, now: float = 0.0) -> bool:
        """A host's token appeared; True if that claim is now the owner (the robot was free and, with a lab
        key, the claim's request had already arrived)."""
        self.hosts.add(claim)
        if self.key is not None and self.requests.pop(claim, 0.0) <= now:
            return False
        return self._grant(claim, now)

    def _grant(self, claim: int, now: float) -> bool:
        if self.owner or claim in self.ended:
            return False
        self.owner, self.released, self.renewed, self.lease_ended = claim, 0, now, False
        self.sequence = SequenceCheck()
        self.applied = self.accepted = self.dropped = self.foreign = self.invalid = self.foreign_claim = 0  # per claim
        self.foreign_reason = None
        return True

    def _end(self, lease_ended: bool = False) -> int:
        claim = self.owner
        self.owner, self.released, self.lease_ended = 0, claim, lease_ended
        self.ended.append(claim)
        self.unsaid_end = self.status(0, 0.0)
        return claim

    def host_left(self, claim: int) -> bool:
        """A host's token went; True if it was the owner's (the claim ended: stop the wheels)."""
        self.hosts.discard(claim)
        self.requests.pop(claim, None)
        if claim != self.owner:
            return False
        self._end()
        return True

    def expire(self, now: float) -> int:
        """End the owner's claim if its run did not renew it for ``lease`` s (with a lab key); the claim that
        ended (stop the wheels), else 0."""
        if self.key is None or not self.owner or now - self.renewed <= self.lease:
            return 0
        return self._end(lease_ended=True)

    def check(self, payload: bytes, now: float, what: str) -> WheelCommand | None:
        """The command in ``payload`` to apply: the owner's, in order and in time, or a stop of the owner's (or
        of the claim that just ended); None for a claim request (granted if it can be); else ``MessageError``
        (counted here: ``invalid``, ``foreign`` or the owner's ``dropped``)."""
        try:
            command = decode_wheels(payload)
        except MessageError:
            self.invalid += 1
            raise
        name = f"wheel command {command.seq} of claim {claim_text(command.claim)}"
        if self.key is not None and not self.key.verify(self.command_key, payload[:WHEELS_BODY], payload[WHEELS_BODY:]):
            self._refuse(command.claim, Drop.UNAUTHENTICATED)
            raise MessageError(Drop.UNAUTHENTICATED, f"{name}: its MAC does not check with this robot side's lab key "
                                                     f"{self.key.path} (not from a run of this lab); refused")
        stop = command.left == 0.0 and command.right == 0.0
        if command.release:
            return self._release(command, what)
        if command.seq == 0:
            return self._request(command, now, what, name)
        if command.claim == self.released and not self.owner:  # its last stops, overtaken by the token's going
            if stop:
                return command
            raise MessageError(Drop.LATE, f"{name}: arrived after its claim ended")
        if not self.owner or command.claim != self.owner:
            self._refuse(command.claim)
            holder = f"claim {claim_text(self.owner)}" if self.owner else "no claim"
            raise MessageError(Drop.FOREIGN, f"{name}: {what} obeys {holder}; refused")
        if stop and command.seq <= self.sequence.last:  # a stop whatever its number: never locked out
            self.accepted += 1
            return command
        try:
            self.sequence.check(command.seq, f"wheel command {command.seq}")
            if not stop:
                check_command_deadline(command, now)
        except MessageError:
            self.dropped += 1
            raise
        self.accepted += 1
        self.renewed = now  # fresh (a number never seen): only its run can have sent it
        return command

    def _release(self, command: WheelCommand, what: str) -> None:
        """The owner's MAC'd release ends its claim, however late (ending a claim, as stopping, is always safe; a
        replay ends a claim that ended already). A repeat of an ended claim's release is ignored."""
        if command.claim == self.owner:
            self._end()
            return None
        if command.claim in self.ended:
            return None
        self._refuse(command.claim)
        raise MessageError(Drop.FOREIGN, f"release of claim {claim_text(command.claim)}: {what} obeys "
                                         f"{'claim ' + claim_text(self.owner) if self.owner else 'no claim'}; refused")

    def _refuse(self, claim: int, reason: Drop = Drop.FOREIGN) -> None:
        self.foreign += 1
        self.foreign_claim, self.foreign_reason = claim, reason

    def _request(self, command: WheelCommand, now: float, what: str, name: str) -> None:
        """A claim request (authenticated): granted if its token is there and the robot free; remembered until
        its deadline if the token has not arrived yet (Zenoh may deliver data ahead of a token)."""
        if command.left != 0.0 or command.right != 0.0:
            self.invalid += 1
            raise MessageError(Drop.MALFORMED, f"{name}: a claim request (number 0) with speeds")
        try:
            check_command_deadline(command, now)
        except MessageError as error:  # the run is told why (its clock and this one's apart), not left guessing
            if command.claim != self.owner:
                self._refuse(command.claim, error.reason)
            raise
        if command.claim == self.owner:
            self.renewed = now  # a renewal, in time: at most a replay within its validity extends the lease
            return None
        if command.claim in self.hosts and self._grant(command.claim, now):
            return None
        if self.owner or command.claim in self.ended:
            self._refuse(command.claim)
            holder = f"claim {claim_text(self.owner)}" if self.owner else "no claim (this one ended)"
            raise MessageError(Drop.FOREIGN, f"claim request of claim {claim_text(command.claim)}: {what} obeys "
                                             f"{holder}; refused")
        if len(self.requests) >= ENDED_KEPT:
            self.requests.pop(next(iter(self.requests)))
        self.requests[command.claim] = command.deadline
        return None

    def record_applied(self, seq: int) -> None:
        self.applied = max(self.applied, seq)

    def statuses(self, seq: int, now: float, flags: int = 0) -> list[Status]:
        """The statuses due now, numbered from ``seq``: the end of the last claim first if no status said it yet
        (another claim was granted before one went out), then the robot side's current one."""
        said = [] if self.unsaid_end is None or not self.owner else [
            replace(self.unsaid_end, seq=seq, stamp=now, flags=self.unsaid_end.flags | flags)]
        self.unsaid_end = None
        return said + [self.status(seq + len(said), now, flags)]

    def status(self, seq: int, now: float, flags: int = 0) -> Status:
        if self.lease_ended and not self.owner:
            flags |= STATUS_LEASE_ENDED
        flags |= refusal_flags(self.foreign_reason)
        return Status(seq, self.owner, self.applied, self.accepted, self.dropped, self.foreign, self.invalid,
                      self.foreign_claim, now, flags, 0 if self.owner else self.released)


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
    release_seen: bool = False  # the robot side said (status) that this claim ended: the stop window is watched
    releasing: bool = False  # the run is releasing its claim: the robot side's saying it ended is expected
    lease_ended: bool = False  # the robot side ended this claim because its lease ran out
    refusal: Drop | None = None  # why the robot side refused this run's claim request (in its words), before the grant
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
            if status.owner == 0 and status.released == self.claim and self.granted:
                self.release_seen, self.status = True, status  # its final counts: the stop window included
                self.lease_ended = bool(status.flags & STATUS_LEASE_ENDED)
                self._check_applied(status, sent)
                if not self.releasing:
                    raise NotDriving(self.ended_early())
                return
            self.other_owner = status.owner
            if status.foreign_claim == self.claim and not self.granted:
                self.refusal = status.refusal
            return
        self.granted, self.status, self.other_owner = True, status, 0
        if status.flags & STATUS_POSES:  # only the claimed robot side says how to tell its poses
            self.echoes = True
        self._check_applied(status, sent)
        received = status.accepted + status.dropped
        if received >= REFUSED_VERDICT_AFTER and status.dropped > status.accepted:
            raise NotDriving(f"the robot side refused most of this run's commands: accepted {status.accepted}, dropped "
                             f"{status.dropped} of {received} received (late, duplicate or out of order: see its log)")

    def ended_early(self) -> str:
        """Why the robot side ended this run's claim before the run released it."""
        if self.lease_ended:
            why = (f"no renewal of it reached the robot side for the claim's lease of {CLAIM_LEASE:g} s (the run "
                   "stalled, or its messages were lost on the way)")
        else:
            why = "its token went (the robot side saw this run's Zenoh session end)"
        return f"its robot side ended this run's claim {claim_text(self.claim)}: {why}"

    def _check_applied(self, status: Status, sent: int) -> None:
        if status.applied > sent:
            raise NotDriving(f"the robot side applied command {status.applied} of this run's claim, but the run sent "
                             f"only {sent}: someone else drives it with this run's claim")

    def interference(self) -> str:
        """Who else tried to drive the robot, as the robot side reported it ("" if nobody)."""
        status = self.status
        if status is None:
            return ""
        return describe_interference(status.foreign, status.invalid, claim_text(status.foreign_claim))


class LeaseRenewal:
    """A run's renewals of its granted claim, every ``LEASE_RENEW_PERIOD`` on a thread of their own: the lease
    holds while the run lives, whatever it does between its commands (its start, its end), and runs out
    when the run is killed or frozen. Stopped (and joined) before the release, so none follows it."""

    def __init__(self, renew: Callable[[], None], period: float = LEASE_RENEW_PERIOD) -> None:
        self._renew, self._period = renew, period
        self._stopped = threading.Event()
        self._thread = threading.Thread(target=self._run, name="claim lease renewal", daemon=True)
        self._thread.start()

    def _run(self) -> None:
        while not self._stopped.wait(self._period):
            self._renew()

    def stop(self) -> None:
        self._stopped.set()
        self._thread.join()


# the robot side's refusals of a run's claim request that waiting cannot mend: another lab key, clocks apart
REQUEST_REFUSALS = (Drop.UNAUTHENTICATED, Drop.LATE, Drop.FUTURE)


def refused_request(refusal: Drop | None, claim: int, key: str) -> str:
    """What the robot side saw of a run's claim requests, in words, when it refused them (``REQUEST_REFUSALS``)."""
    name = f"its robot side refused this run's claim {claim_text(claim)}"
    if refusal is Drop.LATE:
        return (f"{name}: its requests arrived after their deadline by the robot side's clock (each valid for "
                f"{CLAIM_REQUEST_VALIDITY:g} s): the robot side's clock is ahead of this host's by more than "
                f"{CLAIM_REQUEST_VALIDITY:g} s; synchronize the clocks (NTP, chrony)")
    if refusal is Drop.FUTURE:
        return (f"{name}: its requests' deadlines were more than {MAX_COMMAND_AHEAD:g} s ahead by the robot side's "
                "clock: the robot side's clock is behind this host's by more than "
                f"{MAX_COMMAND_AHEAD - CLAIM_REQUEST_VALIDITY:g} s; synchronize the clocks (NTP, chrony)")
    return (f"{name}: the MAC of its requests does not check with the robot side's lab key (this run uses {key}; "
            "give both sides the same file: docs/hil.md, \"Who can start the robot\")")


def describe_interference(foreign: int, invalid: int, foreign_claim: str) -> str:
    """The robot side's refusals in words (also for the run's summary table, from the link statistics)."""
    parts = []
    if foreign:
        parts.append(f"{foreign} commands of other claims (the last of claim {foreign_claim})")
    if invalid:
        parts.append(f"{invalid} invalid commands")
    return "the robot side refused " + " and ".join(parts) if parts else ""
