"""The zenoh-bridge-ros2dds convention: how a DDS-based ROS 2 graph appears on Zenoh through
eclipse-zenoh/zenoh-plugin-ros2dds (``ros2_name_to_key_expr``, ``src/ros2_utils.rs``; README,
"Namespace" and "Configuration").

* Key = the ROS name without its leading "/", behind the bridge's ``namespace`` if it has one:
  ``/vrpn_mocap/m3pi_3/pose`` -> ``vrpn_mocap/m3pi_3/pose``, or ``botX/cmd_vel`` for ``/cmd_vel`` with
  ``namespace: "/botX"``. No domain, type or hash in the key.
* Payload = the DDS sample as the bridge takes it (``dds_takecdr``): CDR with its 4-byte encapsulation
  header, exactly what rmw_zenoh sends as payload. No attachment on topics.
* Routes: the bridge creates a Zenoh subscriber (Zenoh -> DDS) for each DDS reader it discovers, and a
  Zenoh publisher for each DDS writer: a plain Zenoh ``put`` on the key reaches the robot's
  ``/cmd_vel`` subscriber, a plain subscriber on the key gets the motion capture's poses. Its own
  liveliness tokens (``@/<zid>/@ros2_lv/...``) are between bridges; a Zenoh application needs none.
"""

from __future__ import annotations


def topic_key(namespace: str, topic: str) -> str:
    """``vrpn_mocap/m3pi_3/pose`` for ``/vrpn_mocap/m3pi_3/pose``; ``botX/cmd_vel`` with namespace ``/botX``."""
    return "/".join(part for part in (namespace.strip("/"), topic.strip("/")) if part)
