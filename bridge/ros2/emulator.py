"""The m3pi emulator speaking ROS 2 (``platoon m3pi-emulator --ros2``): for each robot whose config has a
``[vehicles.K.ros2]`` table it publishes the pose as the motion capture's ROS driver would (a
PoseStamped, or an Odometry, in the tracker's frame, stamped when taken, best effort as vrpn_mocap's
``SensorDataQoS``) and obeys Twist / TwistStamped commands as a differential-drive base would, through
rmw_zenoh's or zenoh-bridge-ros2dds' convention. A direction without a topic keeps our protocol.

A ROS command has no deadline, no number and no claim: each is applied until ``command_timeout``
after it arrived (diff_drive_controller's ``cmd_vel_timeout``), and numbered here in arrival order,
afresh per claim (``EmulatedRobot.accept_unclaimed``). Whoever may put on the command topic's key
drives the robot, as on a real ROS robot: Zenoh access control on that key is what guards it
(docs/hil.md, "Your lab"), and such a robot publishes no status of ours. Liveliness token and host
tokens stay ours: a run's claim token still puts the robot back on its mark for the next run, and a
pose in our protocol still echoes the claim; a pose on a ROS topic carries none.
"""

from __future__ import annotations

import sys
from dataclasses import replace
from typing import Any, Callable, Sequence

import zenoh

from fmus.realtime import pacing_helper

from ..emulator import Emulator, EmulatorSettings, RobotSpec
from ..protocol import MessageError, Pose
from . import messages, rmw_zenoh
from .link import RosLink
from .node import RosNode


class RosEmulator(Emulator):
    """``Emulator`` with robot ``i`` on ROS 2 topics when ``links[i]`` is a ``RosLink``."""

    def __init__(self, robots: Sequence[RobotSpec], settings: EmulatorSettings, config: zenoh.Config,
                 links: Sequence[RosLink | None], say: Callable[[str], None] = lambda text: print(text, file=sys.stderr,
                                                                                             flush=True)) -> None:
        super().__init__(robots, settings, config, say)
        self.links = list(links)
        for robot, link in zip(self.robots, self.links):
            robot.echoes_poses = link is None or not link.pose_topic
            if link is not None and link.command_topic:  # a ROS command carries no MAC: its token claims the robot
                robot.claim.key = None

    def _declare_robot(self, session: zenoh.Session, index: int, resources: list) -> tuple[Any, Any]:
        link = self.links[index]
        if link is None:
            return super()._declare_robot(session, index, resources)
        keys = self.robots[index].spec.keys
        node = RosNode(session, replace(link.graph, node=f"m3pi_emulator_{keys.robot}"))
        resources.append(node)
        resources.append(session.liveliness().declare_token(keys.alive))
        status = None  # commands on a ROS topic carry no claim: nothing to report
        # the codecs written now: the first command is decoded under the lock the timing loop waits for
        messages.prepare(*[typename for topic, typename in ((link.command_topic, link.command_type),
                                                            (link.pose_topic, link.pose_type)) if topic])
        if link.command_topic:
            commands = link.command_topic
            key = node.subscriber(commands, link.command_type, self._on_twist(index), reliability=rmw_zenoh.RELIABLE,
                                  depth=10)
        else:
            commands, key = keys.wheels, keys.wheels
            status = session.declare_publisher(keys.status, express=True)
            resources.append(session.declare_subscriber(keys.wheels, self._on_command(index)))
        if link.pose_topic:
            pose, publisher = link.pose_topic, node.publisher(link.pose_topic, link.pose_type,
                                                              reliability=rmw_zenoh.BEST_EFFORT, depth=5)
        else:
            pose, publisher = keys.pose, session.declare_publisher(keys.pose, express=True)
        self.say(f"m3pi-emulator robot {keys.robot}: configured, pose on {pose} at {self.settings.rate:g} Hz, "
                 f"commands on {commands} ({link.graph.convention}: key {key})")
        return publisher, status

    def _encode_pose(self, index: int, pose: Pose) -> bytes:
        link = self.links[index]
        if link is None or not link.pose_topic:
            return super()._encode_pose(index, pose)
        x, y, heading = link.frame.invert(pose.x, pose.y, pose.heading)
        robot = self.robots[index]  # sampled just now: its wheel speeds (right, left) are the pose's
        linear, angular = messages.wheels_to_twist(robot.state[4], robot.state[3], robot.spec.dynamics.track)
        return messages.encode_pose(link.pose_type, pose.stamp, x, y, heading, linear=linear, angular=angular)

    def _on_twist(self, index: int) -> Callable[[zenoh.Sample], None]:
        link, robot = self.links[index], self.robots[index]
        assert link is not None

        def receive(sample: zenoh.Sample) -> None:
            pacing_helper()  # holds the lock the timing loop needs (bridge.emulator)
            payload = sample.payload.to_bytes()
            with self._lock:
                now = self.clock()
                try:
                    linear, angular = messages.decode_twist(payload, link.command_type)
                    left, right = messages.twist_to_wheels(linear, angular, robot.spec.dynamics.track)
                except MessageError as error:
                    robot.refuse(error)
                    return
                robot.accept_unclaimed(left, right, now)
        return receive
