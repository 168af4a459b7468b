"""The config tables for ROS 2 (docs/hil.md, "Your lab"): ``[vehicles.K.ros2]`` (a live vehicle's pose
and/or commands on ROS 2 topics) and ``[ros2]`` (publish the whole run to ROS 2). Kept apart from
config.py, which includes them, so that the ROS rules sit together; names are checked as ROS 2 checks
them (design.ros2.org, "Topic and Service name mapping"): a fully qualified topic, a plain node name.
"""

from __future__ import annotations

import re
from typing import Literal

from pydantic import BaseModel, ConfigDict, Field, model_validator

_TOPIC = re.compile(r"^(/[A-Za-z_][A-Za-z0-9_]*)+$")
_NODE = re.compile(r"^[A-Za-z_][A-Za-z0-9_]*$")
_NAMESPACE = re.compile(r"^(/[A-Za-z_][A-Za-z0-9_]*)*$")

Convention = Literal["rmw_zenoh", "bridge_dds"]


class _Strict(BaseModel):
    # built when first used, as the config's tables (orchestrator/scenario/config_types.py, StrictModel)
    model_config = ConfigDict(extra="forbid", strict=True, frozen=True, allow_inf_nan=False, defer_build=True)


class Ros2Rule(ValueError):
    pass


def _check(pattern: re.Pattern, value: str | None, key: str, expected: str) -> None:
    if value is not None and not pattern.match(value):
        raise Ros2Rule(f"{key} = {value!r}: expected {expected}")
    if value is not None and "__" in value:  # ROS 2 reserves repeated underscores (rcl_validate_topic_name)
        raise Ros2Rule(f"{key} = {value!r}: ROS 2 forbids repeated underscores (\"__\") in names")


TOPIC_RULE = 'a fully qualified ROS 2 topic such as "/vrpn_mocap/m3pi_3/pose" (segments of letters, digits, "_")'
NAMESPACE_RULE = 'a ROS 2 namespace such as "/bot3", or "" for none'


class Ros2Frame(_Strict):
    """The tracker's frame in the path's: rotate by ``yaw`` (rad) about the tracker's origin, then shift."""

    x: float = Field(0.0, ge=-1e6, le=1e6)
    y: float = Field(0.0, ge=-1e6, le=1e6)
    yaw: float = Field(0.0, ge=-10.0, le=10.0)


class _Graph(_Strict):
    convention: Convention = "rmw_zenoh"
    domain: int = Field(0, ge=0, le=232, description="ROS_DOMAIN_ID (rmw_zenoh)")
    namespace: str = Field("", description="zenoh-bridge-ros2dds namespace (bridge_dds)")
    node: str | None = Field(None, description="our ROS node's name")
    node_namespace: str = Field("", description="our ROS node's namespace (rmw_zenoh's graph); \"\": the root")

    @model_validator(mode="after")
    def _names(self) -> "_Graph":
        _check(_NAMESPACE, self.namespace, "namespace", NAMESPACE_RULE)
        _check(_NAMESPACE, self.node_namespace, "node_namespace", NAMESPACE_RULE)
        _check(_NODE, self.node, "node", "a ROS 2 node name (letters, digits, '_', not starting with a digit)")
        if self.namespace and self.convention == "rmw_zenoh":  # it would be ignored: say so rather than drop it
            raise Ros2Rule(f"namespace = {self.namespace!r} is zenoh-bridge-ros2dds' key prefix (convention = "
                        "\"bridge_dds\" only); under rmw_zenoh a namespace is part of each topic: write it into "
                        f"the topics ({self.namespace.rstrip('/')}/cmd_vel), and node_namespace puts the run's node in it")
        return self


class VehicleRos2(_Graph):
    """``[vehicles.K.ros2]``: this live vehicle's pose and/or commands on ROS 2 topics."""

    pose_topic: str | None = None
    pose_type: Literal["PoseStamped", "Odometry"] = "PoseStamped"
    command_topic: str | None = None
    # Twist: what most differential-drive bases take on cmd_vel (TurtleBot, Gazebo's diff drive, Nav2's output
    # before Jazzy, Humble's diff_drive_controller unstamped); TwistStamped for diff_drive_controller from Jazzy on
    command_type: Literal["Twist", "TwistStamped"] = "Twist"
    command_stamp: Literal["zero", "now"] = "zero"
    command_frame_id: str = Field("base_link", pattern=r"^[A-Za-z_][A-Za-z0-9_/]*$",
                                  description="a TwistStamped's header.frame_id (the robot's base frame)")
    frame: Ros2Frame = Ros2Frame()

    @model_validator(mode="after")
    def _topics(self) -> "VehicleRos2":
        _check(_TOPIC, self.pose_topic, "pose_topic", TOPIC_RULE)
        _check(_TOPIC, self.command_topic, "command_topic", TOPIC_RULE)
        if not (self.pose_topic or self.command_topic):
            raise Ros2Rule("pose_topic and command_topic both unset: set at least one (the other direction keeps "
                        "our protocol)")
        return self


class RunRos2(_Graph):
    """``[ros2]``: publish every vehicle's pose (PoseStamped) and a TFMessage to ROS 2 while the run goes."""

    publish: bool = False
    topic_prefix: str = Field("/platoon", description="poses on <topic_prefix>/vehicleK/pose")
    frame_id: str = Field("world", pattern=r"^[A-Za-z_][A-Za-z0-9_/]*$")
    rate: float = Field(50.0, gt=0.0, le=1000.0, description="messages per second at most")
    connect: list[str] = Field(default_factory=list)
    listen: list[str] = Field(default_factory=list)
    zenoh_config: str | None = None

    @model_validator(mode="after")
    def _prefix(self) -> "RunRos2":
        _check(_TOPIC, self.topic_prefix, "topic_prefix", TOPIC_RULE)
        if self.publish and not (self.connect or self.listen or self.zenoh_config):
            raise Ros2Rule("publish = true needs connect, listen or zenoh_config: where the ROS 2 graph's Zenoh is")
        return self
