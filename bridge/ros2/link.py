"""A live vehicle whose pose comes from a ROS 2 topic and/or whose commands go to one.

``RosLink`` says which: a pose topic (``geometry_msgs/msg/PoseStamped``, e.g. vrpn_mocap's
``/vrpn_mocap/<body>/pose``, or ``nav_msgs/msg/Odometry``) and a command topic
(``geometry_msgs/msg/TwistStamped``, what ros2_controllers' diff_drive_controller takes on
``~/cmd_vel`` from Jazzy on, or ``Twist``), either of which may be left out to keep our own protocol
for that direction, and the graph (rmw_zenoh or zenoh-bridge-ros2dds, ``node.RosGraph``).

``RosLiveVehicle`` is ``bridge.live.LiveVehicle`` with that seam filled in:

* a pose's heading is the quaternion's yaw, its stamp the header's; ``frame`` moves it from the
  tracker's frame into the path's (rotate by ``frame.yaw`` about the tracker's origin, then shift by
  ``frame.x``, ``frame.y``). ROS poses carry no sequence number: the stamp in µs stands for one, so a
  pose whose stamp is not newer than the last accepted one's is dropped as ``duplicate`` or
  ``out_of_order``; age checks are as for our poses.
* a wheel command becomes ``linear.x = (left + right) / 2``, ``angular.z = (right - left) / track``.
  A ROS command has no deadline: it is published every step, zero on every stop, and the robot's own
  timeout (diff_drive_controller's ``cmd_vel_timeout``, 0.5 s by default) stops it if commands cease.
  A TwistStamped is stamped zero (the controller stamps it on arrival) or with the host's clock
  (``command_stamp = "now"``, for robots whose clocks are synchronized with the host's).
* with ROS commands there is no robot-side liveliness token or status of ours to wait for, and no
  claim: the first valid pose is what the host waits for, the pose timeout what declares the robot
  lost. The run still declares its claim token (an emulator in ``--ros2`` mode takes it as our
  robots do), but a ROS topic carries no claim id, so the robot obeys whoever may put on the command
  topic's key, and a pose topic's poses cannot be told from another publisher's: Zenoh access
  control on those keys is what guards them (docs/hil.md, "Your lab"). A direction left on our
  protocol keeps every check of ``bridge.claim``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Literal

import zenoh

from ..live import LiveVehicle, tls_hint
from ..protocol import Pose, WheelCommand
from . import messages, rmw_zenoh
from .node import RosGraph, RosNode


@dataclass(frozen=True)
class FrameTransform:
    """The tracker's frame in the path's: rotate by ``yaw`` (rad) about the origin, then shift by (x, y) (m)."""

    x: float = 0.0
    y: float = 0.0
    yaw: float = 0.0

    def apply(self, x: float, y: float, heading: float) -> tuple[float, float, float]:
        c, s = math.cos(self.yaw), math.sin(self.yaw)
        return c * x - s * y + self.x, s * x + c * y + self.y, heading + self.yaw

    def invert(self, x: float, y: float, heading: float) -> tuple[float, float, float]:
        """The inverse of ``apply``: path frame -> tracker frame (the emulator publishes in the tracker's)."""
        c, s = math.cos(self.yaw), math.sin(self.yaw)
        dx, dy = x - self.x, y - self.y
        return c * dx + s * dy, -s * dx + c * dy, heading - self.yaw


@dataclass(frozen=True)
class RosLink:
    """Which ROS 2 topics one live vehicle uses (``None``: our own protocol in that direction)."""

    graph: RosGraph = field(default_factory=RosGraph)
    pose_topic: str | None = None
    pose_type: str = messages.POSE_STAMPED
    command_topic: str | None = None
    command_type: str = messages.TWIST
    command_stamp: Literal["zero", "now"] = "zero"
    frame: FrameTransform = field(default_factory=FrameTransform)
    frame_id: str = "base_link"  # a TwistStamped's header.frame_id (diff_drive_controller users expect the base's)

    def describe(self) -> str:
        parts = []
        if self.pose_topic:
            parts.append(f"pose {self.pose_topic} ({self.pose_type.rsplit('/', 1)[-1]})")
        if self.command_topic:
            parts.append(f"commands {self.command_topic} ({self.command_type.rsplit('/', 1)[-1]})")
        return ", ".join(parts) + f" via {self.graph.convention}"


class RosLiveVehicle(LiveVehicle):
    """A live vehicle on ROS 2 topics (see the module docstring)."""

    def __init__(self, *args, ros: RosLink, **kwargs) -> None:
        super().__init__(*args, **kwargs)
        self.ros = ros
        self.what = f"robot {self.settings.robot} ({self.ros.describe()})"
        self.state.who = f"{self.what}"
        self._node: RosNode | None = None
        self._ros_publisher = None
        self._graph: dict[str, dict[str, str]] = {}  # rmw_zenoh: the graph's subscriptions, by liveliness key
        self._zid = ""  # our session's Zenoh id

    def _ros_node(self, session: zenoh.Session) -> RosNode:
        if self._node is None:
            self._node = RosNode(session, self.ros.graph)
            self._resources.append(self._node)
        return self._node

    def _open_commands(self, session: zenoh.Session) -> None:
        if not self.ros.command_topic:
            super()._open_commands(session)
            return
        messages.prepare(self.ros.command_type)  # its encoder written now, not in the first paced step
        self._ros_publisher = self._ros_node(session).publisher(self.ros.command_topic, self.ros.command_type)
        self._publisher = self._ros_publisher
        self._alive = True  # no token of ours on a ROS robot: its first pose says it is there
        if self.ros.graph.convention == "rmw_zenoh":  # the graph says who subscribes, as `ros2 topic info` reads it
            self._zid = str(session.zid())  # our own node's subscriptions are not the robot's
            self._resources.append(session.liveliness().declare_subscriber(
                f"{rmw_zenoh.ADMIN_SPACE}/{self.ros.graph.domain}/**", self._on_graph, history=True))

    def _on_graph(self, sample: zenoh.Sample) -> None:
        key = str(sample.key_expr)
        fields = rmw_zenoh.parse_entity_token(key)
        if fields is None or fields["kind"] != rmw_zenoh.SUBSCRIPTION or fields["zid"] == self._zid:
            return
        with self._lock:
            if sample.kind == zenoh.SampleKind.PUT:
                self._graph[key] = fields
            else:
                self._graph.pop(key, None)

    def _subscriptions(self, topic: str | None = None) -> list[dict[str, str]]:
        with self._lock:
            return [fields for fields in self._graph.values() if topic is None or fields["topic"] == topic]

    def _unheard(self) -> bool:
        """Under rmw_zenoh, nobody subscribes to the command topic yet (the graph says so; a DDS graph behind
        zenoh-bridge-ros2dds does not: there, a robot that does not move says it, ``LiveVehicle``)."""
        return (bool(self.ros.command_topic) and self.ros.graph.convention == "rmw_zenoh"
                and not self._subscriptions(self.ros.command_topic))

    def _nearby(self) -> str:
        """The subscribed topics of the domain, those most like the command topic first (a misspelling shows)."""
        import difflib

        topics = sorted({fields["topic"] for fields in self._subscriptions()})
        close = difflib.get_close_matches(self.ros.command_topic or "", topics, n=5, cutoff=0.0)
        return ", ".join(close) if close else "nothing"

    def _open_poses(self, session: zenoh.Session) -> None:
        if not self.ros.pose_topic:
            super()._open_poses(session)
            return
        messages.prepare(self.ros.pose_type)  # its decoder written before the first pose arrives
        self.pose_key = self._ros_node(session).subscriber(self.ros.pose_topic, self.ros.pose_type, self._on_pose)

    def _decode_pose(self, sample: zenoh.Sample, received: float) -> Pose:
        if not self.ros.pose_topic:
            return super()._decode_pose(sample, received)
        pose = messages.decode_pose(sample.payload.to_bytes(), self.ros.pose_type)
        x, y, heading = self.ros.frame.apply(pose.x, pose.y, pose.heading)
        # its number is its stamp in µs: the sequence check (after the age check, so that a pose stamped in
        # the future cannot lock the real ones out) then drops repeated and older stamps
        return Pose(round(pose.stamp * 1e6), 0, pose.stamp, x, y, heading)

    def _publish_command(self, command: WheelCommand) -> None:
        if not self.ros.command_topic:
            super()._publish_command(command)
            return
        linear, angular = messages.wheels_to_twist(command.left, command.right, self.dynamics.track)
        stamp = self.clock() if self.ros.command_stamp == "now" else 0.0
        self._ros_publisher.put(messages.encode_twist(self.ros.command_type, linear, angular, stamp, self.ros.frame_id))

    def _unanswered_hint(self) -> str:
        if not self.ros.command_topic:
            return super()._unanswered_hint()
        return (f" (commands on {self.ros.command_topic} via {self.ros.graph.convention}: is that the topic the robot "
                "subscribes to, with that type? ros2 topic info -v on the robot's side)")

    def _robot_timeout(self) -> float | None:
        if not self.ros.command_topic:
            return super()._robot_timeout()
        return None  # a ROS robot's own cmd_vel_timeout, not known here

    def _load_key(self):
        if not self.ros.command_topic:
            return super()._load_key()
        return None  # a ROS command carries no MAC: Zenoh's access control on its key is what guards it

    def _request_claim(self) -> None:
        if not self.ros.command_topic:
            super()._request_claim()

    def _ready(self) -> bool:
        if not self.ros.command_topic:
            return super()._ready()
        # no claim on a ROS topic: nothing grants one; under rmw_zenoh someone must subscribe to its commands
        return self._alive and self._latest is not None and not self._unheard()

    def _holding(self) -> str:
        if not self.ros.command_topic:
            return super()._holding()
        return f"commands on {self.ros.command_topic} (a ROS topic: no claim)"

    def _refusal(self, session: zenoh.Session) -> str | None:
        """Under rmw_zenoh, the robot's subscription to the command topic must take our type: a different
        type (or type hash) is another key, where commands would vanish (that someone subscribes, ``_ready`` waited for)."""
        if not self.ros.command_topic:
            return super()._refusal(session)
        if self.ros.graph.convention != "rmw_zenoh":
            return None
        topic, typename = self.ros.command_topic, self.ros.command_type
        found = self._subscriptions(topic)
        ours = (messages.dds_type_name(typename), messages.type_hash(typename))
        if any((fields["type"], fields["hash"]) == ours for fields in found):
            return None
        theirs = ", ".join(sorted({f"{f['type']} ({f['hash'][:15]}...) by {f['namespace'].rstrip('/')}/{f['node']}"
                                   for f in found}))
        return (f"{self.what}: {topic} is subscribed as {theirs}, not as {ours[0]} ({ours[1][:15]}...): "
                f"set vehicles.{self.name.removeprefix('vehicle')}.ros2.command_type to the robot's type (ros2 topic info {topic})")

    def _awaited(self) -> str:
        if self._latest is not None and self._unheard():
            return (f"{self.what}: a subscriber to {self.ros.command_topic} in ROS domain {self.ros.graph.domain} "
                    f"({self._endpoints()})")
        if not self.ros.pose_topic:
            return super()._awaited()
        return f"{self.what}: a first valid pose on {self.ros.pose_topic} (key {self.pose_key}; {self._endpoints()})"

    def _not_found(self) -> str:
        if self._latest is not None and self._unheard():
            return (f"{self.what}: nobody subscribes to {self.ros.command_topic} in ROS domain {self.ros.graph.domain} "
                    f"within {self.settings.connect_timeout:g} s, so no command would reach the robot (subscribed "
                    f"nearby: {self._nearby()}); set vehicles.{self.name.removeprefix('vehicle')}.ros2.command_topic "
                    "to the robot's (ros2 topic list -t)")
        if not self.ros.pose_topic:
            return super()._not_found()
        counters = self.pose_counters
        return (f"{self.what}: no valid pose on {self.ros.pose_topic} (key {self.pose_key}) within "
                f"{self.settings.connect_timeout:g} s ({counters.received} received, {counters.dropped_total} dropped"
                + (f"; last problem: {counters.last_problem}" if counters.last_problem else "")
                + f"; {self._endpoints()}: is the robot's ROS graph or the emulator (--ros2) reachable? Behind a "
                "Zenoh router (rmw_zenohd, zenoh-bridge-ros2dds) the run must join in client mode: it does when it "
                "only connects, else set mode: \"client\" in its zenoh_config" + tls_hint(self.settings) + ")")
