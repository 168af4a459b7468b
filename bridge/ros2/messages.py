"""ROS 2 messages as bytes: the few types a platoon lab uses, encoded and decoded by ``rosbags``.

``rosbags`` (pure Python, maintained, no ROS install) holds each distribution's message definitions,
serializes them to CDR with the 4-byte encapsulation header ROS 2 puts in front (little-endian:
``00 01 00 00``) and computes each type's RIHS01 hash, which rmw_zenoh puts in its key expressions.
The definitions of the types used here are the same in Humble, Jazzy and Kilted (same hashes), so one
store serves them all.

A pose is reduced to what a platoon vehicle needs, (stamp, x, y, heading): the heading is the yaw of
the orientation quaternion, the stamp the header's. Anything that does not decode, or decodes to a
non-finite number or a quaternion that is not one, raises ``bridge.protocol.MessageError`` with the
reason the receiver counts.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import lru_cache
from typing import Any

from rosbags.typesys import Stores, get_typestore

from ..protocol import MAX_PAYLOAD, Drop, MessageError

POSE_STAMPED = "geometry_msgs/msg/PoseStamped"
ODOMETRY = "nav_msgs/msg/Odometry"
TWIST = "geometry_msgs/msg/Twist"
TWIST_STAMPED = "geometry_msgs/msg/TwistStamped"
TF_MESSAGE = "tf2_msgs/msg/TFMessage"

POSE_TYPES = {"PoseStamped": POSE_STAMPED, "Odometry": ODOMETRY}
COMMAND_TYPES = {"Twist": TWIST, "TwistStamped": TWIST_STAMPED}
MAX_MESSAGE = 4 * MAX_PAYLOAD  # an Odometry is 724 bytes (two 36-double covariances); more is not a pose


@lru_cache(maxsize=1)
def typestore() -> Any:
    """The message definitions (Jazzy's; identical for these types in Humble and Kilted)."""
    return get_typestore(Stores.ROS2_JAZZY)


def type_hash(typename: str) -> str:
    """``RIHS01_<sha256 hex>``: the type hash of REP-2011 that rmw_zenoh puts in keys and tokens."""
    return typestore().hash_rihs01(typename)


def dds_type_name(typename: str) -> str:
    """``pkg/msg/T`` -> ``pkg::msg::dds_::T_``, the type name as declared in DDS (rmw_zenoh's keys)."""
    package, kind, name = typename.split("/")
    return f"{package}::{kind}::dds_::{name}_"


@dataclass(frozen=True)
class StampedPose:
    """A planar pose from a ROS message: ``stamp`` in s (the header's), x, y in m, heading in rad."""

    stamp: float
    x: float
    y: float
    heading: float


def _time(stamp: float) -> Any:
    types = typestore().types
    seconds = math.floor(stamp)
    nanoseconds = min(int(round((stamp - seconds) * 1e9)), 999_999_999)
    return types["builtin_interfaces/msg/Time"](sec=int(seconds), nanosec=nanoseconds)


def _header(stamp: float, frame_id: str) -> Any:
    return typestore().types["std_msgs/msg/Header"](stamp=_time(stamp), frame_id=frame_id)


def _pose(x: float, y: float, heading: float) -> Any:
    types = typestore().types
    half = 0.5 * heading  # a rotation about z by the heading
    orientation = types["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=math.sin(half), w=math.cos(half))
    return types["geometry_msgs/msg/Pose"](position=types["geometry_msgs/msg/Point"](x=x, y=y, z=0.0),
                                           orientation=orientation)


def encode_pose(typename: str, stamp: float, x: float, y: float, heading: float, frame_id: str = "world",
                child_frame_id: str = "base_link", linear: float = 0.0, angular: float = 0.0) -> bytes:
    """A PoseStamped or an Odometry of a planar pose, as CDR bytes; an Odometry's twist (``linear`` m/s along
    the body's x, ``angular`` rad/s about z) is in ``child_frame_id``, the body's frame, as REP-105 has it;
    covariances zero (unknown)."""
    store, types = typestore(), typestore().types
    header, pose = _header(stamp, frame_id), _pose(x, y, heading)
    if typename == POSE_STAMPED:
        message = types[POSE_STAMPED](header=header, pose=pose)
    elif typename == ODOMETRY:
        import numpy as np

        vector = types["geometry_msgs/msg/Vector3"]
        twist = types["geometry_msgs/msg/Twist"](linear=vector(x=linear, y=0.0, z=0.0),
                                                 angular=vector(x=0.0, y=0.0, z=angular))
        message = types[ODOMETRY](
            header=header, child_frame_id=child_frame_id,
            pose=types["geometry_msgs/msg/PoseWithCovariance"](pose=pose, covariance=np.zeros(36)),
            twist=types["geometry_msgs/msg/TwistWithCovariance"](twist=twist, covariance=np.zeros(36)))
    else:
        raise ValueError(f"{typename}: not a pose type ({', '.join(POSE_TYPES.values())})")
    return bytes(store.serialize_cdr(message, typename))


def yaw(qx: float, qy: float, qz: float, qw: float) -> float:
    """The heading (rotation about z, rad) of a unit quaternion: atan2(2(wz + xy), 1 - 2(y² + z²))."""
    return math.atan2(2.0 * (qw * qz + qx * qy), 1.0 - 2.0 * (qy * qy + qz * qz))


def _deserialize(payload: bytes, typename: str, what: str) -> Any:
    if len(payload) > MAX_MESSAGE:
        raise MessageError(Drop.OVERSIZED, f"{what}: {len(payload)} bytes, more than {MAX_MESSAGE}")
    try:
        return typestore().deserialize_cdr(payload, typename)
    except Exception as error:  # rosbags raises struct, index, unicode and assertion errors on bad bytes
        raise MessageError(Drop.MALFORMED, f"{what}: not a CDR {typename} ({type(error).__name__}: {error})") from None


def decode_pose(payload: bytes, typename: str) -> StampedPose:
    """(stamp, x, y, heading) of a PoseStamped or Odometry, or ``MessageError`` saying why not."""
    message = _deserialize(payload, typename, typename.rsplit("/", 1)[-1])
    pose = message.pose if typename == POSE_STAMPED else message.pose.pose
    stamp = message.header.stamp.sec + message.header.stamp.nanosec * 1e-9
    p, q = pose.position, pose.orientation
    values = {"stamp": stamp, "x": p.x, "y": p.y, "qx": q.x, "qy": q.y, "qz": q.z, "qw": q.w}
    bad = [f"{name} = {value}" for name, value in values.items() if not math.isfinite(value)]
    if bad:
        raise MessageError(Drop.NON_FINITE, f"{typename}: {', '.join(bad)} (not finite)")
    norm = math.sqrt(q.x * q.x + q.y * q.y + q.z * q.z + q.w * q.w)
    if abs(norm - 1.0) > 1e-3:
        raise MessageError(Drop.MALFORMED, f"{typename}: orientation quaternion of norm {norm:.6g}, not a rotation")
    return StampedPose(stamp, p.x, p.y, yaw(q.x, q.y, q.z, q.w))


def encode_twist(typename: str, linear: float, angular: float, stamp: float = 0.0, frame_id: str = "") -> bytes:
    """A Twist or TwistStamped with ``linear.x`` (m/s) and ``angular.z`` (rad/s), the rest zero."""
    store, types = typestore(), typestore().types
    vector = types["geometry_msgs/msg/Vector3"]
    twist = types[TWIST](linear=vector(x=linear, y=0.0, z=0.0), angular=vector(x=0.0, y=0.0, z=angular))
    if typename == TWIST:
        message = twist
    elif typename == TWIST_STAMPED:
        message = types[TWIST_STAMPED](header=_header(stamp, frame_id), twist=twist)
    else:
        raise ValueError(f"{typename}: not a command type ({', '.join(COMMAND_TYPES.values())})")
    return bytes(store.serialize_cdr(message, typename))


def decode_twist(payload: bytes, typename: str) -> tuple[float, float]:
    """(linear.x, angular.z) of a Twist or TwistStamped, or ``MessageError``."""
    message = _deserialize(payload, typename, typename.rsplit("/", 1)[-1])
    twist = message if typename == TWIST else message.twist
    linear, angular = twist.linear.x, twist.angular.z
    if not (math.isfinite(linear) and math.isfinite(angular)):
        raise MessageError(Drop.NON_FINITE, f"{typename}: linear.x = {linear}, angular.z = {angular} (not finite)")
    return linear, angular


def encode_tf(stamp: float, frame_id: str, children: list[tuple[str, float, float, float]]) -> bytes:
    """A TFMessage with one transform per (child frame, x, y, heading), all from ``frame_id`` at ``stamp``."""
    store, types = typestore(), typestore().types
    transforms = []
    for child, x, y, heading in children:
        pose = _pose(x, y, heading)
        translation = types["geometry_msgs/msg/Vector3"](x=x, y=y, z=0.0)
        transform = types["geometry_msgs/msg/Transform"](translation=translation, rotation=pose.orientation)
        transforms.append(types["geometry_msgs/msg/TransformStamped"](header=_header(stamp, frame_id),
                                                                      child_frame_id=child, transform=transform))
    return bytes(store.serialize_cdr(types[TF_MESSAGE](transforms=transforms), TF_MESSAGE))


def prepare(*typenames: str) -> None:
    """Encode and decode one message of each pose or command type, so that ``rosbags`` writes its (de)serializer
    for it now: it writes each type's code the first time it meets the type (5-7 ms of code generation, holding
    the GIL). Met first inside a paced step (a run's first command) or under the lock an emulated robot's timing
    loop waits for (its first command), they made the start late: in 16 rmw_zenoh runs of ros2_live3.toml the first
    pose after the first command was 0.3-6.3 ms old (median 2.3 ms), and vehicle 3 came 1.1-3.7 mm from the all-FMU
    run; prepared, 0.4-0.9 ms (each run's median age) and 0.33-1.87 mm, five of six under 0.55 mm (2026-12-03). A
    link calls this before its robot is stepped."""
    for typename in typenames:
        if typename in POSE_TYPES.values():
            decode_pose(encode_pose(typename, 0.0, 0.0, 0.0, 0.0), typename)
        elif typename in COMMAND_TYPES.values():
            decode_twist(encode_twist(typename, 0.0, 0.0), typename)
        else:
            raise ValueError(f"{typename}: neither a pose type nor a command type")


def wheels_to_twist(left: float, right: float, track: float) -> tuple[float, float]:
    """(linear.x, angular.z) of a differential drive whose wheels, ``track`` apart, turn at left/right m/s."""
    return 0.5 * (left + right), (right - left) / track


def twist_to_wheels(linear: float, angular: float, track: float) -> tuple[float, float]:
    """(left, right) wheel speeds of a differential drive for (linear.x, angular.z): inverse of the above."""
    return linear - 0.5 * angular * track, linear + 0.5 * angular * track
