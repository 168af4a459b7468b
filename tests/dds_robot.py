"""A ROS 2 robot on DDS, without ROS: one CycloneDDS participant (the ``cyclonedds`` wheel) that does what a
DDS-based ROS 2 robot and its motion capture driver do, for the tests that drive it through a real Zenoh
router with zenoh-plugin-ros2dds (tests/test_zenoh_router.py):

* publishes ``geometry_msgs/msg/PoseStamped`` on ``rt/<pose_topic>`` (best effort, as vrpn_mocap's
  SensorDataQoS) at 200 Hz, the pose of an emulated m3pi (``bridge.emulator.EmulatedRobot``, the
  emulator's own physics, placed where the run starts it);
* subscribes ``geometry_msgs/msg/Twist`` on ``rt/<command_topic>`` (reliable) and obeys it as a
  differential-drive base with a 0.25 s command timeout;
* publishes ``ros_discovery_info`` (``rmw_dds_common/msg/ParticipantEntitiesInfo``, Iron's 16-byte GIDs):
  the participant's GID and, for its one node, the GIDs of its reader and writer, as every ROS 2 rmw
  does. zenoh-plugin-ros2dds builds its ROS graph from it and routes nothing without it.

DDS discovery is confined to loopback by ``CYCLONEDDS_URI`` (the caller sets it; ``LOOPBACK_ONLY``):
no multicast, unicast to 127.0.0.1 only. Run as ``python -m tests.dds_robot CONFIG DOMAIN``; prints "dds robot:
ready" once its entities exist, and its counts and last command (linear.x angular.z) when SIGTERM or SIGINT
ends it.
"""

from dataclasses import dataclass, field
import signal
import sys
import threading
import time
from pathlib import Path

# Cyclone DDS confined to this machine's loopback, no multicast (docs/hil.md, "A real router and DDS bridge")
LOOPBACK_ONLY = ('<CycloneDDS><Domain id="any"><General><Interfaces><NetworkInterface name="lo" multicast="false"/>'
                 '</Interfaces><AllowMulticast>false</AllowMulticast></General><Discovery><ParticipantIndex>auto'
                 '</ParticipantIndex><MaxAutoParticipantIndex>32</MaxAutoParticipantIndex><Peers><Peer '
                 'address="127.0.0.1"/></Peers></Discovery></Domain></CycloneDDS>')


def _types():
    """The ROS 2 message types as DDS declares them (``pkg::msg::dds_::T_``), for cyclonedds.idl."""
    from cyclonedds.idl import IdlStruct
    from cyclonedds.idl.types import array, float64, int32, sequence, uint8, uint32

    @dataclass
    class Time(IdlStruct, typename="builtin_interfaces::msg::dds_::Time_"):
        sec: int32
        nanosec: uint32

    @dataclass
    class Header(IdlStruct, typename="std_msgs::msg::dds_::Header_"):
        stamp: Time
        frame_id: str

    @dataclass
    class Point(IdlStruct, typename="geometry_msgs::msg::dds_::Point_"):
        x: float64
        y: float64
        z: float64

    @dataclass
    class Quaternion(IdlStruct, typename="geometry_msgs::msg::dds_::Quaternion_"):
        x: float64
        y: float64
        z: float64
        w: float64

    @dataclass
    class Pose(IdlStruct, typename="geometry_msgs::msg::dds_::Pose_"):
        position: Point
        orientation: Quaternion

    @dataclass
    class PoseStamped(IdlStruct, typename="geometry_msgs::msg::dds_::PoseStamped_"):
        header: Header
        pose: Pose

    @dataclass
    class Vector3(IdlStruct, typename="geometry_msgs::msg::dds_::Vector3_"):
        x: float64
        y: float64
        z: float64

    @dataclass
    class Twist(IdlStruct, typename="geometry_msgs::msg::dds_::Twist_"):
        linear: Vector3
        angular: Vector3

    @dataclass
    class Gid(IdlStruct, typename="rmw_dds_common::msg::dds_::Gid_"):
        data: array[uint8, 16]

    @dataclass
    class NodeEntitiesInfo(IdlStruct, typename="rmw_dds_common::msg::dds_::NodeEntitiesInfo_"):
        node_namespace: str
        node_name: str
        reader_gid_seq: sequence[Gid]
        writer_gid_seq: sequence[Gid]

    @dataclass
    class ParticipantEntitiesInfo(IdlStruct, typename="rmw_dds_common::msg::dds_::ParticipantEntitiesInfo_"):
        gid: Gid
        node_entities_info_seq: sequence[NodeEntitiesInfo] = field(default_factory=list)

    return {name: value for name, value in locals().items() if isinstance(value, type)}


def _user_data(typename: str):
    """The type hash in USER_DATA, as rmw from Iron on writes it for every reader and writer."""
    from cyclonedds.core import Policy

    from bridge.ros2.messages import type_hash

    return Policy.Userdata(f"typehash={type_hash(typename)};".encode())


def main(config_path: str, domain: int) -> None:
    import math

    from cyclonedds.core import InstanceState, Policy, Qos, ReadCondition, SampleState, ViewState, WaitSet
    from cyclonedds.util import duration
    from cyclonedds.domain import DomainParticipant
    from cyclonedds.pub import DataWriter
    from cyclonedds.sub import DataReader
    from cyclonedds.topic import Topic

    from bridge.emulator import EmulatedRobot, EmulatorSettings
    from bridge.ros2 import messages
    from orchestrator.cli.hil import emulated_links, emulated_robots
    from orchestrator.cli.plain import load_config

    config, _ = load_config(Path(config_path), [])
    spec, link = emulated_robots(config, [3])[0], emulated_links(config, [3], "bridge_dds")[0]
    t = _types()
    participant = DomainParticipant(domain)
    pose_topic = Topic(participant, f"rt{link.pose_topic}", t["PoseStamped"])
    command_topic = Topic(participant, f"rt{link.command_topic}", t["Twist"])
    poses = DataWriter(participant, pose_topic, qos=Qos(Policy.Reliability.BestEffort, Policy.History.KeepLast(5),
                                                        _user_data(messages.POSE_STAMPED)))
    commands = DataReader(participant, command_topic, qos=Qos(Policy.Reliability.Reliable(duration(seconds=1)),
                                                              Policy.History.KeepLast(10), _user_data(messages.TWIST)))
    discovery = DataWriter(participant, Topic(participant, "ros_discovery_info", t["ParticipantEntitiesInfo"]),
                           qos=Qos(Policy.Reliability.Reliable(duration(seconds=1)), Policy.Durability.TransientLocal,
                                   Policy.History.KeepLast(1)))

    def gid(entity) -> object:
        return t["Gid"](list(entity.guid.bytes))

    node = t["NodeEntitiesInfo"]("/", "m3pi_3_base", [gid(commands)], [gid(poses)])
    discovery.write(t["ParticipantEntitiesInfo"](gid(participant), [node]))
    robot = EmulatedRobot(spec, EmulatorSettings(command_timeout=0.25), lambda text: print(text, flush=True))
    robot.host_arrived(1, time.time())  # what commands it: whoever may write its topic (no claim on DDS)
    received, last = 0, (math.nan, math.nan)
    stop = threading.Event()
    for signum in (signal.SIGTERM, signal.SIGINT):
        signal.signal(signum, lambda *_: stop.set())
    # woken by a command or by the next pose's time, not by polling: a process that wakes a thousand times a
    # second loses the CPU to busy neighbours for hundreds of ms (poses 150-350 ms old beside three busy loops)
    waitset = WaitSet(participant)
    waitset.attach(ReadCondition(commands, SampleState.NotRead | ViewState.Any | InstanceState.Any))
    print("dds robot: ready", flush=True)
    period, next_pose = 1.0 / 200.0, time.time()
    while not stop.is_set():
        waitset.wait(max(int((next_pose - time.time()) * 1e9), 0))
        now = time.time()
        for twist in commands.take(N=100):
            if isinstance(twist, t["Twist"]):
                received += 1
                left, right = messages.twist_to_wheels(twist.linear.x, twist.angular.z, spec.dynamics.track)
                last = (twist.linear.x, twist.angular.z)
                robot.accept_unclaimed(left, right, now)
        if now >= next_pose:
            pose = robot.sample(now, None)
            x, y, heading = link.frame.invert(pose.x, pose.y, pose.heading)
            seconds = math.floor(pose.stamp)
            stamp = t["Time"](int(seconds), min(int((pose.stamp - seconds) * 1e9), 999_999_999))
            orientation = t["Quaternion"](0.0, 0.0, math.sin(0.5 * heading), math.cos(0.5 * heading))
            poses.write(t["PoseStamped"](t["Header"](stamp, "world"), t["Pose"](t["Point"](x, y, 0.0), orientation)))
            next_pose = max(next_pose + period, now)
    print(f"dds robot: commands received {received}", flush=True)
    print(f"dds robot: last command {last[0]} {last[1]}", flush=True)  # linear.x, angular.z: 0.0 0.0 is a stop


if __name__ == "__main__":
    signal.signal(signal.SIGINT, signal.SIG_DFL)
    main(sys.argv[1], int(sys.argv[2]))
