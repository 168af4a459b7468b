"""ROS 2 over Zenoh: message encoding (``messages``), the two ways ROS 2 meets Zenoh (``rmw_zenoh``,
``bridge_dds``, chosen through ``conventions``), a minimal ROS node (``node``) and the live vehicle's
pose source and command sink on ROS topics (``link``). No ROS installation is needed: messages are
encoded by ``rosbags`` (pure Python), keys and attachments follow rmw_zenoh's design document."""
