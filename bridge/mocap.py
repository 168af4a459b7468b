"""Motion capture without ROS (``platoon mocap``): rigid bodies from a Vicon, OptiTrack, Qualisys or VRPN
system, read through libmotioncapture's Python binding (``motioncapture``), published on Zenoh as
robot poses: in our pose format on ``<prefix>/m3pi/<id>/pose`` (bridge.protocol) or as
``geometry_msgs/msg/PoseStamped`` on a ROS 2 topic (bridge.ros2, either convention).

Each frame is stamped with the Unix time at which the binding handed it over (it exposes no capture
time: the system's own latency, a few ms, is not in the stamp). A body's heading is the yaw of its
orientation, its position is moved into the path's frame by ``frame`` (bridge.ros2.link.FrameTransform).
A body absent from a frame, or with a non-finite pose (occluded), is not published for that frame: a
robot that disappears goes silent, and the run's ``pose_timeout`` stops it. The first loss and each
return of a body are said on stderr.

libmotioncapture's ``connect(type, options)`` takes these options (src/motioncapture.cpp):
``vicon``: hostname; ``optitrack``: hostname, interface_ip, port_command (1510); ``qualisys``:
hostname, port (22222); ``vrpn``: hostname; ``mock``: rigid_bodies
(``"name(x,y,z,qw,qx,qy,qz);..."``, fixed poses), frequency (Hz).
"""

from __future__ import annotations

import math
import sys
import threading
import time
from dataclasses import dataclass
from typing import Any, Callable, Iterable, Iterator, Mapping, Sequence

import zenoh

from .protocol import Pose, RobotKeys, encode_pose
from .ros2 import messages
from .ros2.link import FrameTransform
from .ros2.node import RosGraph, RosNode

SYSTEMS = ("vicon", "optitrack", "qualisys", "vrpn", "mock")

# a body's reading: x, y, z (m), qx, qy, qz, qw
Reading = tuple[float, float, float, float, float, float, float]


class MocapError(RuntimeError):
    """The motion capture could not be reached or configured; the text names the system and host."""


@dataclass(frozen=True)
class BodyMap:
    """Rigid body ``body`` of the motion capture is robot ``robot``; with ROS 2 output, on ``topic``."""

    body: str
    robot: int
    topic: str | None = None


def read_frames(system: str, options: Mapping[str, str], stop: threading.Event) -> Iterator[tuple[float, dict[str, Reading]]]:
    """(stamp, {body: reading}) for each frame of ``system`` until ``stop`` is set."""
    try:
        import motioncapture
    except ImportError:
        raise MocapError("the motioncapture package is not installed: pip install 'platoon-cosim[mocap]'") from None
    if system not in SYSTEMS:
        raise MocapError(f"--system {system}: expected one of {', '.join(SYSTEMS)}")
    try:
        source = motioncapture.connect(system, dict(options))
    except RuntimeError as error:
        raise MocapError(f"{system} at {options.get('hostname', 'localhost')}: {error}") from None
    while not stop.is_set():
        source.waitForNextFrame()
        stamp = time.time()
        bodies = {}
        for name, body in source.rigidBodies.items():
            p, q = body.position, body.rotation
            bodies[name] = (float(p[0]), float(p[1]), float(p[2]), float(q.x), float(q.y), float(q.z), float(q.w))
        yield stamp, bodies


class MocapPublisher:
    """Publishes the mapped bodies of each frame as robot poses (see the module docstring)."""

    def __init__(self, session: zenoh.Session, bodies: Sequence[BodyMap], prefix: str = "platoon",
                 graph: RosGraph | None = None, frame: FrameTransform = FrameTransform(),
                 frame_id: str = "world", say: Callable[[str], None] = lambda text: print(text, file=sys.stderr,
                                                                                           flush=True)) -> None:
        self.bodies, self.frame, self.frame_id, self.say = list(bodies), frame, frame_id, say
        self.node = RosNode(session, graph) if graph is not None else None
        self._publishers: dict[str, Any] = {}
        for body in self.bodies:
            if self.node is not None:
                if not body.topic:
                    raise MocapError(f"body {body.body}: no ROS 2 topic to publish it on")
                self._publishers[body.body] = self.node.publisher(body.topic, messages.POSE_STAMPED,
                                                                  depth=5, reliability=2)
            else:
                self._publishers[body.body] = session.declare_publisher(RobotKeys(prefix, body.robot).pose, express=True)
        self.sequence = {body.body: 0 for body in self.bodies}
        self.present = {body.body: False for body in self.bodies}

    def where(self, body: BodyMap, prefix: str = "platoon") -> str:
        return body.topic if self.node is not None and body.topic else RobotKeys(prefix, body.robot).pose

    def publish(self, stamp: float, readings: Mapping[str, Reading]) -> list[str]:
        """Publish this frame's mapped bodies; returns the names published."""
        published = []
        for body in self.bodies:
            reading = readings.get(body.body)
            seen = reading is not None and all(math.isfinite(v) for v in reading)
            if seen != self.present[body.body]:
                self.present[body.body] = seen
                self.say(f"mocap: body {body.body} (robot {body.robot}) " + ("tracked" if seen else
                         "lost: not published until it is tracked again"))
            if not seen:
                continue
            x, y, _, qx, qy, qz, qw = reading
            x, y, heading = self.frame.apply(x, y, messages.yaw(qx, qy, qz, qw))
            self.sequence[body.body] += 1
            if self.node is not None:
                payload = messages.encode_pose(messages.POSE_STAMPED, stamp, x, y, heading, frame_id=self.frame_id)
            else:
                payload = encode_pose(Pose(self.sequence[body.body], 0, stamp, x, y, heading))
            self._publishers[body.body].put(payload)
            published.append(body.body)
        return published

    def close(self) -> None:
        if self.node is not None:
            self.node.close()
        else:
            for publisher in self._publishers.values():
                publisher.undeclare()


def run_mocap(frames: Iterable[tuple[float, Mapping[str, Reading]]], publisher: MocapPublisher,
              duration: float | None = None) -> int:
    """Publish every frame of ``frames`` (until it ends or ``duration`` s passed); returns the frame count."""
    start, count = time.monotonic(), 0
    for stamp, readings in frames:
        publisher.publish(stamp, readings)
        count += 1
        if duration is not None and time.monotonic() - start >= duration:
            break
    return count
