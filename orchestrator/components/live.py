"""The orchestrator's side of hardware in the loop: which vehicles are live, and what their links report.

A config marks vehicle K live with ``[vehicles.K] endpoint = "zenoh"``; here that becomes a
``bridge.live.LiveVehicle`` with the very parameter values the Vehicle FMU would have received (its
declared defaults, then the scenario's), its inputs and outputs named as the FMU's. During the run,
orchestrator/observers/hil_link.py moves what the live components saw into the trace. The bridge
knows Zenoh, not the trace.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from orchestrator.components.fmu import UnpackedFmu
from fmus.component import Component
from orchestrator.scenario.scenario import ComponentSpec
from orchestrator.scenario.wiring import vehicle_name

if TYPE_CHECKING:
    from orchestrator.scenario.config import Config



class LiveRunError(ValueError):
    """A run option that cannot work with live vehicles (e.g. the native engine)."""


def live_names(config: Config) -> set[str]:
    return {vehicle_name(k) for k in config.live_vehicles()}


def check_live_options(config: Config, engine: str, trace_writer: str) -> None:
    """Live vehicles run on the Python engine (the native core steps FMUs only), with the inline writer."""
    if not config.live_vehicles():
        return
    names = ", ".join(sorted(live_names(config)))
    if engine != "python":
        raise LiveRunError(f"--engine {engine}: {names} is a live robot (endpoint = \"zenoh\"); live runs use the "
                           "python engine (the default when a config has a live vehicle)")
    if trace_writer == "process":
        raise LiveRunError(f"--trace-writer process: {names} is a live robot; live runs encode the trace inline "
                           "(use auto or inline)")


def live_settings(config: Config, vehicle: int):
    """Where vehicle ``vehicle``'s robot is and how patient the host is with it (a ``bridge.live.LiveSettings``)."""
    from bridge.live import LiveSettings  # Zenoh is imported only by runs that need it
    from bridge.session import session_mode

    override, hil = config.override(vehicle), config.hil
    connect, listen = tuple(override.connect or ()), tuple(override.listen or ())
    return LiveSettings(
        robot=config.robot_id(vehicle),
        prefix=override.prefix or hil.prefix,
        connect=connect,
        listen=listen,
        zenoh_config=override.zenoh_config,
        # a ROS 2 graph's Zenoh is a router (rmw_zenohd, zenoh-bridge-ros2dds): join it as a client
        mode=session_mode(connect, listen) if override.ros2 is not None else "peer",
        pose_timeout=hil.pose_timeout,
        connect_timeout=hil.connect_timeout,
        command_validity=hil.command_validity,
        max_pose_age=hil.max_pose_age,
        allow_insecure=hil.allow_insecure,
        lab_key=hil.lab_key,
    )


def ros_link(config: Config, vehicle: int):
    """Vehicle ``vehicle``'s ROS 2 topics (a ``bridge.ros2.link.RosLink``), or None without ``[vehicles.K.ros2]``."""
    table = config.override(vehicle).ros2
    if table is None:
        return None
    from bridge.ros2.link import FrameTransform, RosLink
    from bridge.ros2.messages import COMMAND_TYPES, POSE_TYPES
    from bridge.ros2.node import RosGraph

    graph = RosGraph(table.convention, table.domain, table.namespace, table.node or f"platoon_{vehicle_name(vehicle)}",
                     table.node_namespace or "/")
    return RosLink(graph, table.pose_topic, POSE_TYPES[table.pose_type], table.command_topic,
                   COMMAND_TYPES[table.command_type], table.command_stamp,
                   FrameTransform(table.frame.x, table.frame.y, table.frame.yaw), table.command_frame_id)


def start_pose_lines(config: Config) -> list[str]:
    """Where to put each live robot before the run: its start pose in the config's (the path's) frame and,
    for a pose from a ROS 2 topic, in the tracker's frame the motion capture reports (``frame`` undone)."""
    import math

    from orchestrator.scenario.scenario import initial_states

    states, lines = initial_states(config), []
    for vehicle in config.live_vehicles():
        x, y, heading, _ = states[vehicle - 1]
        line = (f"{vehicle_name(vehicle)} (robot {config.robot_id(vehicle)}) starts at x = {x:.3f} m, y = {y:.3f} m, "
                f"heading {math.degrees(heading):.1f} deg in the config's frame")
        ros = ros_link(config, vehicle)
        if ros is not None and ros.pose_topic:
            tx, ty, th = ros.frame.invert(x, y, heading)
            line += f"; x = {tx:.3f} m, y = {ty:.3f} m, heading {math.degrees(th):.1f} deg in the tracker's ({ros.pose_topic})"
        lines.append(line + ": place it there")
    return lines


def live_component(spec: ComponentSpec, fmu: UnpackedFmu, config: Config, vehicle: int) -> Component:
    """The live robot standing in for ``spec``'s Vehicle FMU."""
    from bridge.live import LiveVehicle

    settings = live_settings(config, vehicle)
    inputs = [v.name for v in fmu.description.modelVariables if v.causality == "input"]
    outputs = [v.name for v in fmu.description.modelVariables if v.causality == "output"]
    starts = fmu.start_values()
    arguments = (spec.name, {**starts, **spec.parameters}, inputs, outputs, [float(starts[n]) for n in inputs], settings)
    ros = ros_link(config, vehicle)
    if ros is not None:  # poses and/or commands on ROS 2 topics
        from bridge.ros2.link import RosLiveVehicle

        return RosLiveVehicle(*arguments, ros=ros)
    return LiveVehicle(*arguments)
