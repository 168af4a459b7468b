"""The m3pi emulator: a stand-in for the robots and the motion capture, speaking the bridge's protocol.

Each emulated robot is the Pololu m3pi of ``fmus.model.dynamics.M3piDynamics.drive`` (the very
physics the Vehicle FMU integrates): two wheels following their speed commands with a first-order
motor lag, clipped to the wheel speed limit, and a unicycle body. It runs in wall-clock time:

* wheel commands arrive on ``<prefix>/m3pi/<id>/cmd/wheels``, are checked (size, version, finite,
  claim, sequence, deadline: ``bridge.claim.RobotClaim``) and applied after ``command_latency`` (the
  radio); they hold until the next one. Only the claim that holds the robot is obeyed; the others'
  commands are refused and counted on ``<prefix>/m3pi/<id>/status`` (20 times a second);
* the pose is sampled ``rate`` times a second, gets Gaussian noise (``position_noise`` per axis,
  ``heading_noise``), is stamped with the time it was taken and published ``latency`` later on
  ``<prefix>/m3pi/<id>/pose``, with the number and claim of the last command applied;
* a watchdog stops the wheels (commands of zero; the motors run down with their lag) when the current
  command's deadline passes, when no valid command came for ``command_timeout``, or when the host's
  liveliness token disappears: a robot never keeps driving on a stale command;
* a liveliness token on ``<prefix>/m3pi/<id>/alive`` says the robot is there;
* a new claim (a host's token on ``<prefix>/m3pi/<id>/host/<claim>`` and its request with the lab key's
  MAC, while the robot is free: ``bridge.claim``) puts the robot back on its mark, at rest and waiting,
  so one emulator serves any number of runs one after the other; the claim ends on the run's MAC'd
  release, when its lease runs out (the run stopped renewing it) or when that token goes.

Each robot may differ from the model (``RobotSpec.truth``, from a robot truth file: ``bridge.robot_truth``):
its own wheel gains, motor lag, limit and dead-band (in its ``dynamics``), its own command latency and pose
noise (else the ``EmulatorSettings``' values), and a pose latency its stamps do not show: its poses are
stamped and handed over ``pose_latency`` after the robot was there, as ``platoon mocap`` stamps a frame
when the motion capture hands it over (the model's ``pose_latency``, fmus/model/robot_loop.py), and
published ``latency`` after that stamp. The run never sees that file.

Before its first command a robot stands at its config's initial pose. With ``flying_start`` (the
default) its wheels are set to the config's initial speed at the first command, as the simulated
vehicles start, so a live run is comparable with the all-FMU run; ``flying_start=False`` starts
from rest, as a real robot does.
"""

from __future__ import annotations

import heapq
import itertools
import random
import statistics
import sys
import threading
import time
from collections import deque
from dataclasses import dataclass, field
from typing import Any, Callable, Sequence

import zenoh

from fmus.model.dynamics import M3piDynamics
from fmus.model.integrate import integrate
from fmus.realtime import PacingPriority, pacing_helper

from .claim import RobotClaim, claim_from_key, claim_text
from .lab_key import LabKey
from .robot_truth import RobotTruth
from .protocol import (
    STATUS_POSES,
    LinkCounters,
    MessageError,
    Pose,
    RobotKeys,
    WheelCommand,
    encode_pose,
    encode_status,
)
from .session import open_session, undeclare_all, zenoh_config
from .states import LinkState, StateMachine

PHYSICS_SUBSTEP = 0.001  # s, the longest RK4 substep of the emulated physics
STATUS_PERIOD = 0.05  # s between two status messages of a robot (and one at once when its claim changes)


@dataclass(frozen=True)
class EmulatorSettings:
    rate: float = 200.0  # poses per second (the paper's motion capture: about 200 Hz)
    position_noise: float = 0.0  # m, standard deviation per axis (paper: about 2 mm)
    heading_noise: float = 0.0  # rad, standard deviation (paper: about 2 degrees)
    latency: float = 0.0  # s, pose taken -> pose published
    command_latency: float = 0.0  # s, command received -> applied (the radio link)
    command_timeout: float = 0.25  # s without a valid command: the wheels stop
    flying_start: bool = True
    seed: int | None = None
    lab_key: LabKey | None = None  # the runs' commands must carry its MAC (bridge.lab_key); None: tokens claim
    # s, the runs' command validity (deadline = send time + it): when given, a steady radio: each command is applied
    # command_latency after it was SENT (or on arrival, if later), so the host's own delivery jitter (the Zenoh hop,
    # milliseconds on a loaded machine) does not reach the wheels. A test bench's choice (the calibration tests: their
    # truth is the robot's, not the machine's); by default, as a radio does, command_latency counts from arrival
    steady_radio_validity: float | None = None


SLACK_KEPT = 10_000  # commands whose deadline slack the end-of-run line summarises (100 s at 100 Hz)


@dataclass(frozen=True)
class RobotSpec:
    """One robot to emulate: its id, keys, where it starts, its m3pi physics (the robot's own, when a truth file
    gives them) and its own latencies and noise (``truth``: None values are the emulator's settings)."""

    keys: RobotKeys
    x: float
    y: float
    heading: float
    speed: float
    dynamics: M3piDynamics
    truth: RobotTruth = RobotTruth()

    def link_value(self, key: str, settings: EmulatorSettings) -> float:
        """This robot's ``command_latency``, ``pose_latency`` (the latency its stamps do not show: none unless the
        truth file says), ``position_noise`` or ``heading_noise``."""
        own = getattr(self.truth, key)
        if own is not None:
            return own
        return 0.0 if key == "pose_latency" else getattr(settings, key)


@dataclass
class EmulatedRobot:
    """One robot's physics, command handling and watchdog; every method is called under the emulator's lock."""

    spec: RobotSpec
    settings: EmulatorSettings
    say: Callable[[str], None]
    state: list[float] = field(default_factory=list)  # x, y, heading, v_right, v_left
    time: float = 0.0  # wall-clock time the state describes
    command: tuple[float, float] = (0.0, 0.0)  # (left, right) being applied
    command_seq: int = 0  # the last command applied
    deadline: float = float("inf")
    last_valid: float = 0.0  # when the last valid command arrived
    pending: deque = field(default_factory=deque)  # (apply at, command) in arrival order
    counters: LinkCounters = field(default_factory=LinkCounters)
    pose_seq: int = 0
    claim: RobotClaim = field(default_factory=RobotClaim)
    status_seq: int = 0
    claim_status_time: float = 0.0  # when the last status was made
    claim_changed: bool = False  # a status is due at once
    unclaimed_seq: int = 0  # commands of a source without claims (a ROS 2 topic) numbered here, afresh per claim
    echoes_poses: bool = True  # its poses go out in our protocol, echoing the claim (not on a ROS 2 topic)
    # s of each recent command's deadline left when it arrived: the run sets deadline = sent + command_validity,
    # so command_validity minus this is the hop from the run to the robot side, part of the loop's delay
    slack: deque = field(default_factory=lambda: deque(maxlen=SLACK_KEPT))

    def __post_init__(self) -> None:
        spec = self.spec
        self.state = [spec.x, spec.y, spec.heading, 0.0, 0.0]
        self.claim = RobotClaim(self.settings.lab_key, spec.keys.wheels)
        self.link = StateMachine(f"m3pi-emulator robot {spec.keys.robot}", self._announce)
        self.command_latency, self.pose_latency, self.position_noise, self.heading_noise = (
            spec.link_value(key, self.settings) for key in ("command_latency", "pose_latency", "position_noise",
                                                             "heading_noise"))
        self._warned: set[str] = set()

    def _announce(self, old: LinkState, new: LinkState, reason: str) -> None:
        self.say(f"m3pi-emulator robot {self.spec.keys.robot}: {old.value} -> {new.value} ({reason})")

    def _derivative(self, t: float, s: list[float]) -> list[float]:
        left, right = self.command
        return self.spec.dynamics.drive(s[2], s[3], s[4], right, left, 0.0)

    def _move(self, until: float) -> None:
        if until > self.time:
            if self.link.state in (LinkState.RUNNING, LinkState.STOPPED):
                self.state = integrate(self._derivative, 0.0, self.state, until - self.time, PHYSICS_SUBSTEP)
            self.time = until

    def _stop_wheels(self, at: float, reason: str) -> None:
        self._move(at)
        self.command = (0.0, 0.0)
        self.deadline = float("inf")
        if self.link.state == LinkState.RUNNING:
            self.link.go(LinkState.STOPPED, reason)

    def advance(self, now: float) -> None:
        """Move the robot to ``now``, applying due commands and the watchdog at the instants they fall."""
        while True:
            due = self.pending[0][0] if self.pending else float("inf")
            timeout = self.last_valid + self.settings.command_timeout if self.link.state == LinkState.RUNNING else float("inf")
            stop_at = min(self.deadline, timeout)
            if min(due, stop_at) > now:
                break
            if stop_at <= due:
                self._stop_wheels(stop_at, "command deadline passed" if stop_at == self.deadline
                                  else f"no command for {self.settings.command_timeout:g} s")
            else:
                _, command = self.pending.popleft()
                self._move(due)
                self._apply(command, due)
        self._move(now)

    def _apply(self, command: WheelCommand, at: float) -> None:
        stop = command.left == 0.0 and command.right == 0.0
        if command.deadline <= at and not stop:  # expired on the way (radio latency): never applied; a stop always is
            return
        if self.link.state == LinkState.CONFIGURED and self.settings.flying_start and not stop:
            self.state[3] = self.state[4] = self.spec.speed
        if stop and self.link.state == LinkState.RUNNING:
            self.link.go(LinkState.STOPPED, "stop command")
        elif self.link.state != LinkState.RUNNING and (command.left != 0.0 or command.right != 0.0):
            self.link.go(LinkState.RUNNING, f"command {command.seq}")
        self.command = (command.left, command.right)  # the robot's own dead-band, gains and limit act in drive()
        self.command_seq = command.seq
        self.claim.record_applied(command.seq)
        self.deadline = float("inf") if stop else command.deadline

    def receive(self, payload: bytes, now: float) -> None:
        """A wheel command arrived: check it, then queue it for its application time."""
        self.expire(now)
        owner = self.claim.owner
        try:
            command = self.claim.check(payload, now, f"robot {self.spec.keys.robot}")
        except MessageError as error:
            self.refuse(error)
            return
        if self.claim.owner and self.claim.owner != owner:  # a claim request granted
            self._claimed(self.claim.owner, now)
        elif owner and not self.claim.owner:
            self._ended(owner, now, "its run released it")
        if command is not None:
            self.slack.append(command.deadline - now)
            self.queue(command, now)

    def accept_unclaimed(self, left: float, right: float, now: float) -> None:
        """A command from a source that carries no claim (a ROS 2 topic: what guards it is Zenoh access control
        on its key, docs/hil.md). Numbered here in arrival order, afresh per claim, so that the poses echo
        it as they would a command of ours; held until ``command_timeout`` after it arrived, as a ROS
        robot's own command timeout does."""
        self.unclaimed_seq += 1
        self.queue(WheelCommand(self.unclaimed_seq, now + self.settings.command_timeout, left, right, self.claim.owner),
                   now)

    def refuse(self, error: MessageError) -> None:
        """Count a dropped command; the first of each kind is said."""
        self.counters.drop(error)
        if error.reason.value not in self._warned:
            self._warned.add(error.reason.value)
            self.say(f"m3pi-emulator robot {self.spec.keys.robot}: dropped: {error} (further drops of this kind "
                     "are only counted)")

    def queue(self, command: WheelCommand, now: float) -> None:
        """An accepted command: apply it ``command_latency`` from now (the radio), or from its send time with a
        steady radio (``EmulatorSettings.steady_radio_validity``)."""
        self.counters.accept()
        self.last_valid = now
        self.advance(now)
        validity = self.settings.steady_radio_validity
        if validity is None:
            self.pending.append((now + self.command_latency, command))
        else:  # its send time (never later than now: the deadline is the sender's word), or on arrival if later
            self.pending.append((max(min(command.deadline - validity, now) + self.command_latency, now), command))
        self.advance(now)

    def host_arrived(self, claim: int, now: float) -> None:
        """A host's token appeared: if that makes a claim (the robot free and, with a lab key, the claim's request
        already here), the robot goes back on its mark, at rest, as before a first run."""
        self.expire(now)
        if self.claim.host_appeared(claim, now):
            self._claimed(claim, now)
        elif self.claim.owner and claim != self.claim.owner:
            self.say(f"m3pi-emulator robot {self.spec.keys.robot}: host of claim {claim_text(claim)} appeared while "
                     f"claim {claim_text(self.claim.owner)} holds the robot; its commands are refused")

    def _claimed(self, claim: int, now: float) -> None:
        """A claim was granted: the robot goes back on its mark, at rest, as before a first run."""
        name = f"m3pi-emulator robot {self.spec.keys.robot}"
        self.claim_changed = True
        self._warned.clear()  # each run's log names the first drop of each kind during its claim
        self.say(f"{name}: claimed by {claim_text(claim)}")
        self.pending.clear()
        self.command_seq = self.unclaimed_seq = 0
        if self.link.state == LinkState.CONFIGURED:
            return
        self._stop_wheels(now, "new claim")
        spec = self.spec
        self.state = [spec.x, spec.y, spec.heading, 0.0, 0.0]
        self.link.go(LinkState.CONFIGURED, "a new host appeared: back on the initial pose, waiting for commands")

    def host_gone(self, claim: int, now: float) -> None:
        if self.claim.host_left(claim):
            self._ended(claim, now, "its token went")

    def expire(self, now: float) -> None:
        """End the claim if its run stopped renewing it (``bridge.claim``: killed, frozen, cut off)."""
        ended = self.claim.expire(now)
        if ended:
            self._ended(ended, now, f"its lease of {self.claim.lease:g} s ran out")

    def _ended(self, claim: int, now: float, how: str) -> None:
        """The claim ended: the wheels stop at once, whatever was queued."""
        self.claim_changed = True
        self.advance(now)
        self.pending.clear()
        self.say(f"m3pi-emulator robot {self.spec.keys.robot}: claim {claim_text(claim)} released ({how})")
        self._stop_wheels(now, f"claim ended: {how}")

    def sample(self, now: float, noise: random.Random) -> Pose:
        """The pose the motion capture sees now (with noise), numbered and stamped with the instant the robot's
        state describes (``now``, or later if a command already moved it on)."""
        self.advance(now)
        now = max(now, self.time)
        self.pose_seq += 1
        x, y, heading = self.state[0], self.state[1], self.state[2]
        if self.position_noise > 0.0:
            x += noise.gauss(0.0, self.position_noise)
            y += noise.gauss(0.0, self.position_noise)
        if self.heading_noise > 0.0:
            heading += noise.gauss(0.0, self.heading_noise)
        # stamped as a motion capture that hands a frame over pose_latency after it saw the robot stamps it
        return Pose(self.pose_seq, self.command_seq, now + self.pose_latency, x, y, heading, self.claim.owner)

    def statuses(self, now: float) -> list[bytes]:
        """The status messages due (every ``STATUS_PERIOD``, or at once after a claim change; a claim's end is
        said even when another claim was granted before a status went out)."""
        if not self.claim_changed and now - self.claim_status_time < STATUS_PERIOD:
            return []
        self.claim_changed, self.claim_status_time = False, now
        due = self.claim.statuses(self.status_seq + 1, now, STATUS_POSES if self.echoes_poses else 0)
        self.status_seq += len(due)
        return [encode_status(status) for status in due]


class Emulator:
    """Every emulated robot on one Zenoh session, one timing loop (``run``) and Zenoh's callback threads."""

    def __init__(self, robots: Sequence[RobotSpec], settings: EmulatorSettings, config: zenoh.Config,
                 say: Callable[[str], None] = lambda text: print(text, file=sys.stderr, flush=True),
                 clock: Callable[[], float] = time.time) -> None:
        if settings.rate <= 0:
            raise ValueError(f"rate = {settings.rate}: expected poses per second > 0")
        self.settings, self.config, self.say, self.clock = settings, config, say, clock
        self.robots = [EmulatedRobot(spec, settings, say) for spec in robots]
        self._lock = threading.Lock()
        self._noise = random.Random(settings.seed)
        # (publish at, order, robot index, payload), a heap: each robot's poses wait its own pose latency
        self._outbox: list[tuple[float, int, int, bytes]] = []
        self._order = itertools.count()
        self.stop_event = threading.Event()

    def _on_command(self, index: int) -> Callable[[zenoh.Sample], None]:
        def receive(sample: zenoh.Sample) -> None:
            pacing_helper()  # holds the lock the timing loop needs: not to be preempted holding it
            payload = sample.payload.to_bytes()
            with self._lock:
                self.robots[index].receive(payload, self.clock())
        return receive

    def _on_host(self, index: int) -> Callable[[zenoh.Sample], None]:
        def changed(sample: zenoh.Sample) -> None:
            claim = claim_from_key(str(sample.key_expr))
            if claim is None:
                return
            with self._lock:
                if sample.kind == zenoh.SampleKind.DELETE:
                    self.robots[index].host_gone(claim, self.clock())
                else:
                    self.robots[index].host_arrived(claim, self.clock())
        return changed

    def run(self, duration: float | None = None, ready: Callable[[], None] | None = None) -> None:
        """Emulate until ``stop_event`` is set (or ``duration`` s passed); tokens and session are released."""
        period = 1.0 / self.settings.rate
        with open_session(self.config, "m3pi-emulator") as session:
            resources, publishers, statuses = [], [], []
            for index, robot in enumerate(self.robots):
                pose, status = self._declare_robot(session, index, resources)
                publishers.append(pose)
                statuses.append(status)
                resources.append(session.liveliness().declare_subscriber(robot.spec.keys.hosts, self._on_host(index),
                                                                          history=True))
            resources += publishers + [status for status in statuses if status is not None]
            if ready is not None:
                ready()
            start = self.clock()
            with self._lock:
                for robot in self.robots:
                    robot.time = start
            next_sample = start
            # this loop samples the poses on time and applies the commands: the robot's clock, raised if asked
            priority = PacingPriority("m3pi-emulator: the timing loop")
            if priority.note is not None:
                self.say(priority.note)
            try:
                while not self.stop_event.is_set():
                    with self._lock:
                        # read under the lock: a command taken meanwhile has moved the robots to its own (later)
                        # arrival, and a pose stamped with an earlier instant would show them ahead of its stamp
                        now = self.clock()
                        if duration is not None and now - start >= duration:
                            break
                        if now >= next_sample:
                            for index, robot in enumerate(self.robots):
                                pose = robot.sample(now, self._noise)
                                publish = pose.stamp + self.settings.latency
                                heapq.heappush(self._outbox, (publish, next(self._order), index,
                                                              self._encode_pose(index, pose)))
                            next_sample += period
                            if next_sample < now:  # fell behind (a stalled machine): no burst of catch-up samples
                                next_sample = now + period
                        else:
                            for robot in self.robots:
                                robot.advance(now)
                        for robot in self.robots:
                            robot.expire(now)
                        due = []
                        while self._outbox and self._outbox[0][0] <= now:
                            due.append(heapq.heappop(self._outbox))
                        reports = [(index, report) for index, robot in enumerate(self.robots)
                                   for report in robot.statuses(now)]
                    for _, _, index, payload in due:
                        publishers[index].put(payload)
                    for index, report in reports:
                        if statuses[index] is not None:
                            statuses[index].put(report)
                    wake = min(next_sample, self._outbox[0][0] if self._outbox else next_sample)
                    self.stop_event.wait(max(0.0, min(wake - self.clock(), 0.01)))
            finally:
                priority.restore()
                undeclare_all(resources)
                for robot in self.robots:
                    c = robot.counters
                    slack = (f"; deadline left on arrival {statistics.median(robot.slack) * 1e3:.2f} ms (median of the last "
                             f"{len(robot.slack)})" if robot.slack else "")
                    self.say(f"m3pi-emulator robot {robot.spec.keys.robot}: commands received {c.received}, accepted "
                             f"{c.accepted}, dropped {c.dropped_total} "
                             + " ".join(f"{k}={v}" for k, v in c.dropped.items() if v) + slack)

    # -- the robot side's seam: our protocol here, ROS 2 topics in bridge.ros2.emulator.RosEmulator ----------

    def _declare_robot(self, session: zenoh.Session, index: int, resources: list) -> tuple[Any, Any]:
        """Declare robot ``index``'s command subscriber and liveliness token; return its pose publisher and
        its status publisher (None: a robot side without claims, whose status would say nothing)."""
        keys = self.robots[index].spec.keys
        status = session.declare_publisher(keys.status, express=True)
        resources.append(session.declare_subscriber(keys.wheels, self._on_command(index)))
        resources.append(session.liveliness().declare_token(keys.alive))
        self.say(f"m3pi-emulator robot {keys.robot}: configured, pose on {keys.pose} at "
                 f"{self.settings.rate:g} Hz, commands on {keys.wheels}")
        return session.declare_publisher(keys.pose, express=True), status

    def _encode_pose(self, index: int, pose: Pose) -> bytes:
        return encode_pose(pose)


def run_emulator(robots: Sequence[RobotSpec], settings: EmulatorSettings, connect: Sequence[str] = (),
                 listen: Sequence[str] = (), zenoh_config_file: str | None = None, duration: float | None = None,
                 stop_event: threading.Event | None = None, ready: Callable[[], None] | None = None,
                 make: Callable[..., Emulator] | None = None, allow_insecure: bool = False) -> Emulator:
    """Build (``make(robots, settings, zenoh config)``, default ``Emulator``) and run an emulator until stopped
    (``stop_event``, ``duration``, or KeyboardInterrupt)."""
    emulator = (make or Emulator)(robots, settings, zenoh_config(connect, listen, zenoh_config_file,
                                                                 allow_insecure=allow_insecure))
    if stop_event is not None:
        emulator.stop_event = stop_event
    emulator.run(duration, ready)
    return emulator
