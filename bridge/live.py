"""A live m3pi robot behind the orchestrator's ``Component`` interface: the host side of the link.

``LiveVehicle`` stands where a Vehicle FMU would: same inputs, same outputs, fed by and feeding the
neighbouring FMUs. What it computes is the FMU's own model (``fmus.model.factory.controller_stepper``,
m3pi dynamics, the config's constants: a calibrated config's gains and dead-band too), with the pose replaced by
the robot's measured one:

* each step it takes the newest valid pose, dead-reckons it from the pose's time stamp to now along
  the arc the robot is turning on (``fmus.model.coupling.arc_extrapolate``: this absorbs the motion
  capture's latency as far as the stamp shows it; what a stamp hides is the robot's ``m3pi.pose_latency``,
  fmus.model.robot_loop), evaluates the guidance law there, turns the lateral command into wheel speeds
  (paper eqs. 10-11, ``M3piDynamics.wheel_commands``) and publishes them with a deadline;
* between poses it keeps the controller's own states (the speed setpoint V_s of the speed loop, and
  the wheel speeds the motor-lag model predicts) by integrating the same model over the step;
* its outputs (pose, speed, rates, gap, wheels) come from that state at the end of the step, after
  the master has paced itself to wall-clock time, so they describe the robot at the step's end.

The run claims its robot (``bridge.claim``): a random claim id in its liveliness token and in every
command. Poses of other publishers are dropped as ``foreign``; a robot that applies commands the run
never sent, or refuses most of its commands, ends the run (``NotDriving``), as does another claim
holding the robot at the start.

Faults end the run through ``ComponentError`` naming the robot: its liveliness token gone, or no
valid pose for ``pose_timeout``. Malformed, oversized, non-finite, duplicated, out-of-order, late and
foreign messages are dropped and counted, never used. ``close`` always sends a stop command first,
then releases the claim.
"""

from __future__ import annotations

import math
import threading
import time
from collections import deque
from dataclasses import dataclass
from typing import Any, Callable, Mapping, Sequence

import zenoh

from fmus.model.angles import wrap_angle
from fmus.model.coupling import arc_extrapolate
from fmus.model.dynamics import M3piDynamics
from fmus.model.factory import controller_stepper
from fmus.model.vehicle import VEHICLE_INPUTS
from fmus.component import ComponentError, LiveEvent, LiveRecord, percentile_summary
from fmus.realtime import pacing_helper

from .claim import (
    CLAIM_LEASE,
    CLAIM_REQUEST_VALIDITY,
    GRANT_GRACE,
    REQUEST_REFUSALS,
    HostClaim,
    LeaseRenewal,
    NotDriving,
    claim_text,
    refused_request,
)
from .lab_key import LabKey, LabKeyError, load_lab_key
from .motion_watch import MotionWatch
from .protocol import (
    Drop,
    LinkCounters,
    MessageError,
    Pose,
    RobotKeys,
    WheelCommand,
    check_pose_time,
    decode_pose,
    decode_status,
    encode_wheels,
)
from .session import SessionError, open_session, undeclare_all, zenoh_config
from .states import LinkState, StateMachine

STOP_REPEATS = 3  # a stop command is sent this many times: one lost message must not keep a robot going
# s between the last stop command and the claim's release: Zenoh may deliver the token's removal ahead of
# the data sent just before it, and the robot side then counts the last stop as arriving after its claim
RELEASE_DELAY = 0.02
# s the run waits after releasing its claim for the robot side's status saying so, with the claim's final counts:
# a command the run never sent, applied between its stops and the release, ends the run (exit 1) as mid-run. A
# release that did not arrive is made up for by the lease's end, so the watch outlasts the lease; unconfirmed,
# the run ends with exit 1 saying so (bridge.claim)
RELEASE_WATCH = CLAIM_LEASE + 1.0
CLAIM_REQUEST_PERIOD = 0.1  # s between claim requests while the robot side has not granted the claim
# the numbers of each raw message a link records (``LiveRecord``), in order: known before the link opens, so
# a live view declares these streams before its first viewer connects (orchestrator/observers/hil_link.py)
POSE_FIELDS = ("received", "stamp", "seq", "command_seq", "x", "y", "heading")
COMMAND_FIELDS = ("sent", "seq", "deadline", "left", "right")
RECORD_FIELDS = {"pose": POSE_FIELDS, "command": COMMAND_FIELDS}


@dataclass(frozen=True)
class LiveSettings:
    """Where the robot is and how patient the host is with it (config: ``[vehicles.K]`` and ``[hil]``)."""

    robot: int
    prefix: str = "platoon"
    connect: tuple[str, ...] = ()
    listen: tuple[str, ...] = ()
    zenoh_config: str | None = None
    # the session's Zenoh mode without a zenoh_config: "client" joins a router (rmw_zenohd, zenoh-bridge-ros2dds),
    # which routes everything to it; a peer that listens nowhere, beside a router, is offered the robot's
    # session directly, cannot reach it, and gets nothing (bridge.session.session_mode)
    mode: str = "peer"
    pose_timeout: float = 0.5  # s without a valid pose: the robot is lost
    connect_timeout: float = 10.0  # s to wait at start for the robot's token and first pose
    command_validity: float = 0.1  # s: each command's deadline is its send time plus this
    max_pose_age: float = 0.25  # s: an older pose is dropped as late
    allow_insecure: bool = False  # endpoints off this machine without TLS are allowed (bridge.session)
    lab_key: str | None = None  # the lab key file (bridge.lab_key); None: $PLATOON_LAB_KEY or the user's own

    @property
    def keys(self) -> RobotKeys:
        return RobotKeys(self.prefix, self.robot)


class LiveVehicle:
    """One vehicle of the platoon driven by a live robot (see the module docstring)."""

    realtime = True

    def __init__(
        self,
        name: str,
        parameters: Mapping[str, Any],
        inputs: Sequence[str],
        outputs: Sequence[str],
        input_defaults: Sequence[float],
        settings: LiveSettings,
        clock: Callable[[], float] = time.time,
    ) -> None:
        self.name = name
        self.inputs, self.outputs, self.input_defaults = list(inputs), list(outputs), list(input_defaults)
        unknown = [n for n in self.inputs if n not in VEHICLE_INPUTS]
        if unknown:
            raise ValueError(f"{name}: a live vehicle has no input(s) {', '.join(unknown)}")
        self._attributes = [VEHICLE_INPUTS[n] for n in self.inputs]
        self.stepper = controller_stepper(parameters, 0.0)  # the latencies are the robot's own, out there
        dynamics = self.stepper.model.dynamics
        if not isinstance(dynamics, M3piDynamics):
            raise ValueError(f"{name}: a live robot needs dynamics = \"m3pi\" (got {dynamics.kind!r})")
        self.dynamics: M3piDynamics = dynamics
        self.settings = settings
        self.keys = settings.keys
        self.clock = clock
        self.what = f"robot {settings.robot} ({self.keys.prefix}/m3pi/{settings.robot})"
        self.pose_key = self.keys.pose  # where poses come from (a ROS 2 topic's key in bridge.ros2.link)
        self._lock = threading.Lock()
        self._events: deque[LiveEvent] = deque()
        self._records: deque[LiveRecord] = deque()
        self.state = StateMachine(self.what, self._announce)
        self.pose_counters = LinkCounters()
        self.status_counters = LinkCounters()
        self.claim = HostClaim()
        self._not_driving: str | None = None  # why the robot does not do what this run commands
        self._latest: Pose | None = None
        self._latest_received = 0.0
        self._alive = False
        self._lost: str | None = None
        self._heading = self.stepper.state[2]  # the measured heading, unwrapped (continuous, as the FMU's)
        self._command_seq = 0
        self._sent: dict[int, float] = {}  # send time of commands not yet reflected in a pose
        self.round_trips: list[float] = []  # s, command sent -> first pose taken after the robot applied it
        self.pose_ages: list[float] = []  # s, age of the pose each step used
        self.motion = MotionWatch()  # commanded to move, not moving: the run ends (bridge.motion_watch)
        self._last_sent: float | None = None  # when the last command went out (its deadline guards the robot)
        self.safety_stops = 0  # commands that expired before the next was sent: the robot side stopped its wheels
        self.longest_gap = 0.0  # s, the longest time without a command (robot-side stops)
        self._time = 0.0
        self._looked_at: float | None = None  # when the run last checked the link (each step and output read)
        self._step_size = 0.0  # s of wall time expected between two of those checks (a paced run's step)
        self._warned: set[str] = set()
        self._session: zenoh.Session | None = None
        self._resources: list[Any] = []
        self._publisher: Any = None
        self._stop_sent = False
        self._released = False
        self._releasing = False
        self._key: LabKey | None = None
        self._token: Any = None  # the claim's liveliness token, released last
        self._renewal: LeaseRenewal | None = None  # renews the granted claim until its release
        self._unconfirmed: str | None = None  # why the claim's end was not confirmed (the run then fails)
        self.on_wait: Callable[[str, float], None] | None = None  # (what the start waits for, s left), each second

    # -- events and records for the run (LiveComponent) -----------------------------------------

    def _announce(self, old: LinkState, new: LinkState, reason: str) -> None:
        level = "Error" if new == LinkState.ERROR else "Info"
        self._events.append(LiveEvent(level, f"{self.what}: {old.value} -> {new.value} ({reason})"))

    def drain_events(self) -> list[LiveEvent]:
        return _drain(self._events)

    def drain_records(self) -> list[LiveRecord]:
        return _drain(self._records)

    def link_statistics(self) -> dict[str, Any]:
        return _link_statistics(self.settings.robot, self.state.state.value, self.claim, self._command_seq,
                                self.pose_counters, self.round_trips, self.pose_ages, self.motion.ratio_min,
                                self.safety_stops, self.longest_gap)

    # -- Zenoh callbacks (Zenoh's threads) -------------------------------------------------------

    def _on_pose(self, sample: zenoh.Sample) -> None:
        pacing_helper()  # the stepping thread reads what this thread hands over, under its lock
        if self._releasing:  # the claim is being released: the robot's next poses echo no claim
            return
        received = self.clock()
        try:
            pose = self._decode_pose(sample, received)
            with self._lock:
                self.claim.source(pose)
                check_pose_time(pose, received, self.settings.max_pose_age)
                try:
                    self.claim.accept(pose, self._command_seq)
                except NotDriving as error:
                    self._not_driving = self._not_driving or str(error)
                    return
                self._latest, self._latest_received = pose, received
                self.pose_counters.accept()
                sent = [seq for seq in self._sent if seq <= pose.command_seq]
                if sent:  # the robot applied these commands before the pose was taken
                    self.round_trips.append(received - self._sent[max(sent)])
                    for seq in sent:
                        del self._sent[seq]
            self._records.append(LiveRecord("pose", dict(zip(POSE_FIELDS, (
                received, pose.stamp, pose.seq, pose.command_seq, pose.x, pose.y, pose.heading)))))
        except MessageError as error:
            with self._lock:
                self.pose_counters.drop(error)
            if error.reason.value not in self._warned:  # the first of each kind in the log; all in the counters
                self._warned.add(error.reason.value)
                self._events.append(LiveEvent("Warning", f"{self.what}: dropped a message on {self.pose_key}: "
                                                         f"{error} (further drops of this kind are only counted)"))

    def _on_status(self, sample: zenoh.Sample) -> None:
        if self._released:  # after the release was confirmed (or not): nothing more to learn
            return
        try:
            status = decode_status(sample.payload.to_bytes())
        except MessageError as error:
            with self._lock:
                self.status_counters.drop(error)
            return
        with self._lock:
            self.status_counters.accept()
            try:
                self.claim.robot_status(status, self._command_seq)
            except NotDriving as error:
                self._not_driving = self._not_driving or str(error)

    def _on_liveliness(self, sample: zenoh.Sample) -> None:
        if str(sample.key_expr) != self.keys.alive:
            return
        if sample.kind == zenoh.SampleKind.PUT:
            self._alive = True
        elif self._alive:
            self._lost = f"its liveliness token {self.keys.alive} was dropped (robot side gone)"

    # -- Component --------------------------------------------------------------------------------

    def initialize(self, start_time: float) -> None:
        """Open the session, claim the robot, wait for its token, the claim's grant and a first valid pose."""
        self._time = start_time
        settings = self.settings
        try:
            self._key = self._load_key()
            config = zenoh_config(settings.connect, settings.listen, settings.zenoh_config, mode=settings.mode,
                                  allow_insecure=settings.allow_insecure, connect_wait=settings.connect_timeout)
            self._session = open_session(config, f"{self.name} ({self.what})")
        except (SessionError, LabKeyError) as error:
            unreached = settings.mode == "client" and not settings.zenoh_config and isinstance(error, SessionError)
            hint = (f" (client mode: the router at {list(settings.connect)}, rmw_zenohd, zenoh-bridge-ros2dds or the "
                    f"emulator, did not answer within connect_timeout {settings.connect_timeout:g} s: is it running?)"
                    if unreached else "")
            raise ComponentError(self.name, start_time, str(error) + hint) from None
        session = self._session
        self._open_commands(session)
        self._open_poses(session)
        self._token = session.liveliness().declare_token(self.keys.host(self.claim.claim))  # the claim
        claimed = time.monotonic()
        deadline = claimed + settings.connect_timeout
        shown = None  # the whole seconds left last reported to on_wait
        requested = 0.0
        while not self._ready():
            if time.monotonic() - requested >= CLAIM_REQUEST_PERIOD:  # once granted, each renews the claim's lease
                requested = time.monotonic()
                self._request_claim()
            left = deadline - time.monotonic()
            if self.on_wait is not None and left > 0 and math.ceil(left) != shown:
                shown = math.ceil(left)
                self.on_wait(self._awaited(), left)
            problem = self._start_problem(time.monotonic() - claimed)
            if problem is None and time.monotonic() > deadline:
                problem = self._not_found()
            if problem is not None:
                self._stop_sent = True  # nothing of ours to stop: the robot does not obey this run
                raise self._fail(start_time, problem)
            time.sleep(0.005)
        if self.claim.granted:  # from here to its release the run renews its claim (bridge.claim)
            self._renewal = LeaseRenewal(self._renew_claim)
        refusal = self._refusal(session)
        if refusal is not None:
            self._stop_sent = True  # it cannot hear this run's commands
            raise self._fail(start_time, refusal)
        self.state.go(LinkState.SYNCHRONIZED, f"{self._holding()}, liveliness token and a valid pose received "
                                              f"(pose {self._latest.seq})")
        self._measure()

    def _ready(self) -> bool:
        """The robot is there, obeys this claim, and a pose of it arrived (echoing the claim if its source does)."""
        latest = self._latest
        return (self._alive and self.claim.granted and latest is not None
                and (latest.claim == self.claim.claim or not self.claim.echoes))

    def _start_problem(self, waited: float) -> str | None:
        """Why waiting longer is useless: another claim holds the robot, or the robot side speaks another version."""
        # a claim whose run died holds until its lease ends (a copy of its token holds nothing): wait that long
        if self.claim.other_owner and not self.claim.granted and waited > GRANT_GRACE + CLAIM_LEASE:
            return (f"{self.what} is already driven by another run (its robot side obeys claim "
                    f"{claim_text(self.claim.other_owner)}, not this run's {claim_text(self.claim.claim)}, and it was "
                    f"renewed for longer than the claim's lease of {CLAIM_LEASE:g} s): one run per robot")
        for counters, key in ((self.pose_counters, self.keys.pose), (self.status_counters, self.keys.status)):
            if counters.dropped[Drop.VERSION.value] and not counters.accepted:
                return f"{self.what}: the messages on {key} are of another protocol version ({counters.last_problem})"
        if self.claim.refusal in REQUEST_REFUSALS and waited > GRANT_GRACE:
            return self._not_found()
        return None

    # -- the link's seam: our wheel protocol here, ROS 2 topics in bridge.ros2.link.RosLiveVehicle ----------

    def _open_commands(self, session: zenoh.Session) -> None:
        """Declare the command publisher, and watch the robot side's status and liveliness token."""
        self._publisher = session.declare_publisher(self.keys.wheels, congestion_control=zenoh.CongestionControl.BLOCK,
                                                    express=True)
        self._resources.append(self._publisher)
        self._resources.append(session.declare_subscriber(self.keys.status, self._on_status))
        self._resources.append(session.liveliness().declare_subscriber(self.keys.alive, self._on_liveliness,
                                                                        history=True))

    def _open_poses(self, session: zenoh.Session) -> None:
        self._resources.append(session.declare_subscriber(self.keys.pose, self._on_pose))

    def _decode_pose(self, sample: zenoh.Sample, received: float) -> Pose:
        return decode_pose(sample.payload.to_bytes())

    def _publish_command(self, command: WheelCommand) -> None:
        self._publisher.put(encode_wheels(command, self._key, self.keys.wheels))

    def _load_key(self) -> LabKey | None:
        """The lab key our commands carry the MAC of (a ROS topic carries none: ``RosLiveVehicle``)."""
        return load_lab_key(self.settings.lab_key)

    def _renew_claim(self) -> None:
        """A renewal of the granted claim (a claim request of it); a session already gone renews nothing."""
        try:
            self._request_claim()
        except zenoh.ZError:
            pass

    def _release_claim(self) -> None:
        """The claim's MAC'd release, after the stops (sent as often: one lost must not leave it to the lease)."""
        deadline = self.clock() + self.settings.command_validity
        release = encode_wheels(WheelCommand(0, deadline, 0.0, 0.0, self.claim.claim, release=True), self._key,
                                self.keys.wheels)
        for _ in range(STOP_REPEATS):
            self._publisher.put(release)

    def _request_claim(self) -> None:
        """Ask the robot side for the claim: a command numbered 0, both speeds 0, with the lab key's MAC."""
        deadline = self.clock() + CLAIM_REQUEST_VALIDITY
        self._publisher.put(encode_wheels(WheelCommand(0, deadline, 0.0, 0.0, self.claim.claim), self._key,
                                          self.keys.wheels))

    def _holding(self) -> str:
        """How this run holds the robot, for the log."""
        return f"claim {claim_text(self.claim.claim)} granted"

    def _refusal(self, session: zenoh.Session) -> str | None:
        """Why this run must not drive the robot it found although it is ready (None: it may). Our protocol
        has said all in ``_start_problem``; a ROS 2 topic may be subscribed with another type."""
        return None

    def _endpoints(self) -> str:
        settings = self.settings
        mode = f"zenoh_config {settings.zenoh_config}" if settings.zenoh_config else f"{settings.mode} mode"
        return f"connect={list(settings.connect)} listen={list(settings.listen)}, {mode}"

    def _awaited(self) -> str:
        """What initialize still waits for, and where (for a countdown the run shows)."""
        if not self._alive:
            return f"{self.what}: its liveliness token {self.keys.alive} ({self._endpoints()})"
        if not self.claim.granted:
            return f"{self.what}: its robot side to accept this run's claim {claim_text(self.claim.claim)}"
        return f"{self.what}: a first valid pose on {self.keys.pose} ({self._endpoints()})"

    def _not_found(self) -> str:
        where = self._endpoints()
        if not self._alive:
            cause = tls_listener_hint(self.settings) or ("is `platoon m3pi-emulator` or `platoon m3pi-serial` running?"
                                                         + tls_hint(self.settings))
            return (f"{self.what} did not appear within {self.settings.connect_timeout:g} s: no liveliness token on "
                    f"{self.keys.alive} ({where}; {cause})")
        if not self.claim.granted:
            key = f"lab key {self._key.path}" if self._key is not None else "no lab key"
            if self.claim.refusal in REQUEST_REFUSALS:
                return f"{self.what}: " + refused_request(self.claim.refusal, self.claim.claim, key)
            if self.status_counters.accepted:  # the robot side speaks, and never named this run's claim
                return (f"{self.what} is there but its robot side did not grant this run's claim "
                        f"{claim_text(self.claim.claim)} within {self.settings.connect_timeout:g} s, and its status on "
                        f"{self.keys.status} never named it: its requests on {self.keys.wheels} did not reach it (an "
                        "access-control rule of the lab's Zenoh configs that keeps this host's puts on that key from "
                        "it? docs/hil.md, \"A secure lab\")")
            return (f"{self.what} is there but its robot side did not grant this run's claim "
                    f"{claim_text(self.claim.claim)} within {self.settings.connect_timeout:g} s: no status on "
                    f"{self.keys.status} (a robot side of another protocol version sends none: update it; or an "
                    "access-control rule keeps its status from this host)")
        counters = self.pose_counters
        return (f"{self.what} is there but sent no valid pose on {self.keys.pose} within "
                f"{self.settings.connect_timeout:g} s ({counters.received} received, {counters.dropped_total} dropped"
                + (f"; last problem: {counters.last_problem}" if counters.last_problem else "") + ")")

    def end_initialization(self) -> None:
        pass

    def set_inputs(self, values: Sequence[float]) -> None:
        stepper = self.stepper
        for attribute, value in zip(self._attributes, values):
            setattr(stepper, attribute, float(value))

    def _check_link(self, t: float) -> None:
        if self._lost is not None:
            raise self._fail(t, f"{self.what} lost: {self._lost}")
        if self._not_driving is not None:
            raise self._fail(t, f"{self.what} does not obey this run: {self._not_driving}")
        now = self.clock()
        away, self._looked_at = (0.0 if self._looked_at is None else now - self._looked_at), now
        timeout = self.settings.pose_timeout
        if away > timeout + self._step_size:
            raise self._fail(t, self._stalled(away))
        silent = now - self._latest_received
        if silent > timeout:
            raise self._fail(t, f"{self.what} lost: no valid pose for {silent:.2f} s (pose_timeout {timeout:g} s; "
                                f"{self._drops()})")

    def _drops(self) -> str:
        """The poses dropped so far, by reason: "286 dropped: late 286" (late ones: a slow path to this host)."""
        reasons = self.pose_counters.drop_reasons()
        return f"{self.pose_counters.dropped_total} dropped" + (f": {reasons}" if reasons else "")

    def _stalled(self, away: float) -> str:
        """Why a run whose own steps came ``away`` s apart ends: for that long the robot had no command (its robot
        side stopped it when the last one's deadline passed) and the run did not read its poses; those waiting in
        the network's buffers are too old by now, so the run cannot tell a silent robot from its own stall, and a
        run that went on would step the rest of the platoon through that time at once, beside a robot that stood.
        The cause is this host (a load that starved the run, a suspended process, a paused virtual machine), so
        the message says so instead of blaming the link."""
        return (f"this run itself stalled: {away:.2f} s between two of its steps (step {self._step_size:g} s), "
                f"longer than pose_timeout {self.settings.pose_timeout:g} s: {self.what} went that long without a "
                "command (its robot side stopped it) and its poses went unread (this host was starved by its load, "
                f"suspended or paused; {self._drops()} so far)")

    def _measure(self) -> float:
        """Put the newest measured pose, dead-reckoned to now, into the controller's state; returns its age (s)."""
        with self._lock:
            pose = self._latest
        assert pose is not None
        state, dynamics = self.stepper.state, self.dynamics
        heading = self._heading + wrap_angle(pose.heading - self._heading)
        self._heading = heading
        age = max(0.0, self.clock() - pose.stamp)
        # before the first command the robot stands on its mark: nothing to dead-reckon
        moved = age if self.state.state == LinkState.RUNNING else 0.0
        speed = dynamics.speed(state, 0.0)
        turn_rate = (state[3] - state[4]) / dynamics.track
        x, y, h, _ = arc_extrapolate(pose.x, pose.y, heading, speed, 0.0, turn_rate, moved)
        self.stepper.state = [x, y, h, *state[3:]]
        return age

    def step(self, time_: float, step: float) -> None:
        """Command the robot for [t, t + h] from its pose now; advance the controller's states."""
        self._time, self._step_size = time_, step
        self._check_link(time_)
        if self.state.state != LinkState.RUNNING:
            self.state.go(LinkState.RUNNING, "first step")
        self.pose_ages.append(self._measure())  # the pose this step's command is computed from
        stepper = self.stepper
        _, acceleration, _ = stepper.evaluate(time_, stepper.state)
        right, left = self.dynamics.radio_command(stepper.state[5], acceleration, stepper.added_speed)
        self._watch_motion(time_, left, right)
        self._send(left, right, self.settings.command_validity)
        try:
            stepper.step(time_, step)
        except ValueError as error:
            raise self._fail(time_, str(error)) from None

    def _watch_motion(self, t: float, left: float, right: float) -> None:
        """End the run if the robot's new poses do not answer the commands (``bridge.motion_watch``: judged by
        the poses' stamps, so a pause of the poses is left to ``pose_timeout``)."""
        with self._lock:
            pose = self._latest
        assert pose is not None
        problem = self.motion.observe(self.clock(), pose.stamp, pose.x, pose.y, 0.5 * (left + right),
                                      self.settings.command_validity)
        if problem is not None:
            raise self._fail(t, f"{self.what} is not moving: {problem}{self._unanswered_hint()}")

    def _unanswered_hint(self) -> str:
        """Where the commands went, for the message of a robot that does not move."""
        return f" (commands on {self.keys.wheels})"

    def get_outputs(self) -> list[float]:
        if self.state.state == LinkState.RUNNING:
            self._check_link(self._time)
            self._measure()
        values = self.stepper.outputs()
        return [values[name] for name in self.outputs]

    def _send(self, left: float, right: float, validity: float) -> None:
        self._command_seq += 1
        now = self.clock()
        self._note_safety_stop(now)
        command = WheelCommand(self._command_seq, now + validity, left, right, self.claim.claim)
        self._publish_command(command)
        with self._lock:
            self._sent[command.seq] = now
            if len(self._sent) > 1000:  # a motion capture that does not echo command numbers: keep the newest
                for seq in sorted(self._sent)[:-100]:
                    del self._sent[seq]
        self._records.append(LiveRecord("command", dict(zip(COMMAND_FIELDS, (
            now, command.seq, command.deadline, left, right)))))

    def _note_safety_stop(self, now: float) -> None:
        """A command sent after the previous one's deadline: the robot side stopped its wheels meanwhile (a
        stall of this run). Said in the log once per stall, counted for the summary and the terminal."""
        validity = self._robot_timeout()
        last, self._last_sent = self._last_sent, now
        if last is None or validity is None or now - last <= validity or self._stop_sent:
            return
        gap = now - last
        self.safety_stops += 1
        self.longest_gap = max(self.longest_gap, gap)
        self._events.append(LiveEvent("Warning", f"{self.what}: robot-side safety stop: no command for {gap * 1e3:.0f} ms, "
                                                 f"past its deadline ({validity * 1e3:.0f} ms): the robot stopped its "
                                                 "wheels until this command (the run stalled)"))

    def _robot_timeout(self) -> float | None:
        """How long a command holds on the robot side (None: unknown, a ROS robot's own timeout)."""
        return self.settings.command_validity

    def _fail(self, t: float, reason: str) -> ComponentError:
        """Enter the error state, stop the robot, and return the error to raise."""
        if self.state.state not in (LinkState.ERROR, LinkState.STOPPED):
            self.state.go(LinkState.ERROR, reason)
        self._stop()
        return ComponentError(self.name, t, reason)

    def _stop(self) -> None:
        """Send the stop command (once: after a fault, closing does not send it again)."""
        if self._publisher is None or self._stop_sent:
            return
        self._stop_sent = True
        try:
            for _ in range(STOP_REPEATS):
                self._send(0.0, 0.0, self.settings.command_validity)
        except zenoh.ZError:  # the session is already gone: the robot's own deadline stops it
            pass

    def close(self) -> None:
        """Stop the robot, release the claim and watch the robot until its side says the claim ended, then
        leave Zenoh. Safe to call in any state, any number of times. A command the run never sent, applied
        in that stop window, is a ``ComponentError`` (raised once all is closed), as it would be mid-run."""
        if self._session is None:
            return
        self._stop()
        interference = self.claim.interference()
        if interference:
            self._events.append(LiveEvent("Warning", f"{self.what}: {interference}"))
        time.sleep(RELEASE_DELAY)
        self._release_and_watch()
        self._released = True  # what arrives from now on is not counted: the claim is released
        undeclare_all(self._resources)
        self._publisher = None
        session, self._session = self._session, None
        session.close()
        if self._not_driving is not None and self.state.state != LinkState.ERROR:
            raise self._fail(self._time, f"{self.what} does not obey this run: {self._not_driving} (seen while "
                                         "it stopped)")
        if self._unconfirmed is not None:
            raise self._fail(self._time, self._unconfirmed)
        if self.state.state != LinkState.STOPPED and self.state.state != LinkState.ERROR:
            self.state.go(LinkState.STOPPED, "run ended; stop command sent")

    def _release_and_watch(self) -> None:
        """Release the claim (its MAC'd release, then the token) and wait (``RELEASE_WATCH``) for the robot side's
        status naming the claim as ended: its counts then cover everything applied under the claim, the stop
        window included. Unconfirmed, the run says so and fails in ``close``: the robot may be held still."""
        token, self._token = self._token, None
        if self._renewal is not None:
            self._renewal.stop()
        with self._lock:
            self._releasing = self.claim.releasing = True
        if token is None:
            return
        try:
            if self.claim.granted:
                self._release_claim()
                time.sleep(RELEASE_DELAY)  # the release ahead of the token's going: the robot side says which ended it
            token.undeclare()
        except zenoh.ZError:
            return
        if not self.claim.granted or self._lost is not None:
            return
        deadline = time.monotonic() + RELEASE_WATCH
        while time.monotonic() < deadline and self._lost is None:
            with self._lock:
                if self.claim.release_seen or self._not_driving is not None:
                    return
            time.sleep(0.005)
        if self._lost is None:
            self._unconfirmed = (f"{self.what}: its robot side did not confirm the end of this run's claim "
                                 f"{claim_text(self.claim.claim)} within {RELEASE_WATCH:g} s (no status on "
                                 f"{self.keys.status} naming it released): the robot may still be held for the next "
                                 "run, and what it applied after its last status is not known")
            self._events.append(LiveEvent("Warning", self._unconfirmed))


def tls_listener_hint(settings: LiveSettings) -> str:
    """For a robot that did not appear over plain tcp/: if the far side of a connect endpoint speaks TLS
    (``bridge.tls_probe``: one handshake per endpoint, only now), that this run forgot the lab's TLS; else ""."""
    from .tls_probe import tls_listeners

    secured = tls_listeners(settings.connect)
    if not secured:
        return ""
    return (f"{secured[0]} answers in TLS: the robot side listens with TLS there, so connect with "
            f"tls/{secured[0][len('tcp/'):]} and the lab's zenoh_config (docs/hil.md, \"A secure lab\")")


def tls_hint(settings: LiveSettings) -> str:
    """For a robot that did not appear over TLS: the likely cause, a certificate the other side refuses (the
    handshake fails quietly on Zenoh's side, so the run only sees nothing arrive)."""
    if not any(endpoint.startswith(("tls/", "quic/")) for endpoint in (*settings.connect, *settings.listen)):
        return ""
    return ("; over TLS the likely cause is the certificates: both sides need ones signed by the lab's CA, each "
            "naming its host, and the robot side's must name the host this run connects to (docs/hil.md, "
            "\"A secure lab\"; RUST_LOG=zenoh_link_tls=debug shows the handshake)")


def _link_statistics(robot: int, state: str, claim: HostClaim, command_seq: int, pose_counters: LinkCounters,
                     round_trips: Sequence[float], pose_ages: Sequence[float], ratio_min: float, safety_stops: int,
                     longest_gap: float) -> dict[str, Any]:
    values: dict[str, Any] = {"robot": robot, "state": state, "claim": claim_text(claim.claim), "command.sent": command_seq}
    values["command.safety_stops"], values["command.longest_gap"] = safety_stops, longest_gap
    # the lowest moved / commanded over a judged window (bridge.motion_watch); 0 until one was judged
    values["motion.ratio_min"] = ratio_min if math.isfinite(ratio_min) else 0.0
    values.update(pose_counters.as_dict("pose"))
    values.update(robot_side_counts(claim))
    # every key from the first call on (0 with count 0 until measured): the trace's link stream keeps its fields
    values.update(percentile_summary("round_trip", round_trips, empty=0.0))
    values.update(percentile_summary("pose_age", pose_ages, empty=0.0))
    return values


def initial_link_statistics() -> dict[str, Any]:
    """``LiveVehicle.link_statistics`` before the link opened: the keys of every later call, in order."""
    return _link_statistics(0, LinkState.CONFIGURED.value, HostClaim(), 0, LinkCounters(), [], [], math.inf, 0, 0.0)


def robot_side_counts(claim: HostClaim) -> dict[str, Any]:
    """What the robot side reported about this run's commands and others' (all 0 until its first status)."""
    status = claim.status
    values: dict[str, Any] = {f"command.{name}": getattr(status, name, 0) if status else 0
                              for name in ("accepted", "dropped", "foreign", "invalid")}
    if status is not None and status.foreign_claim:
        values["command.foreign_claim"] = claim_text(status.foreign_claim)
    return values


def _drain(queue: deque) -> list:
    items = []
    while queue:
        items.append(queue.popleft())
    return items
