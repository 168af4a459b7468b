"""``platoon mocap``: a motion capture's rigid bodies as robot poses on Zenoh, without ROS (bridge/mocap.py;
docs/hil.md, "Mocap without ROS"). A long-running process that stops on Ctrl-C or SIGTERM."""

from __future__ import annotations

import math
import threading
from pathlib import Path
from typing import Annotated, Optional

import typer

from orchestrator.cli.common import fail
from orchestrator.cli.hil import AllowInsecure, Endpoints, stop_on_signals


def _pairs(values: list[str], flag: str) -> list[tuple[str, str]]:
    pairs = []
    for value in values:
        key, sep, rest = value.partition("=")
        if not sep or not key or not rest:
            fail(2, f"{flag} {value!r}: expected NAME=VALUE")
        pairs.append((key, rest))
    return pairs


def _frame(text: str):
    from bridge.ros2.link import FrameTransform

    try:
        x, y, yaw = (float(part) for part in text.split(","))
    except ValueError:
        fail(2, f"--frame {text!r}: expected X,Y,YAW (m, m, rad), e.g. 0.5,-1.0,1.5708")
    if not all(math.isfinite(v) for v in (x, y, yaw)):
        fail(2, f"--frame {text!r}: expected finite numbers")
    return FrameTransform(x, y, yaw)


def mocap(
    system: Annotated[str, typer.Option(metavar="SYSTEM", help="vicon, optitrack, qualisys, vrpn (or mock, for a test)")],
    bodies: Annotated[list[str], typer.Option("--body", metavar="NAME=ID", help="publish rigid body NAME as robot ID (repeatable)")],
    host: Annotated[Optional[str], typer.Option(metavar="HOST", help="the motion capture server's host name or IP")] = None,
    options: Annotated[list[str], typer.Option("--option", metavar="KEY=VALUE", help="a libmotioncapture option, e.g. port=22222 (repeatable)")] = [],
    prefix: Annotated[str, typer.Option(metavar="PREFIX", help="Zenoh key prefix of our pose format")] = "platoon",
    ros2: Annotated[Optional[str], typer.Option("--ros2", metavar="CONVENTION", help="publish PoseStamped through rmw_zenoh or bridge_dds instead of our format")] = None,
    topic: Annotated[str, typer.Option(metavar="TOPIC", help="ROS 2 topic per body ({body}: its name), with --ros2")] = "/vrpn_mocap/{body}/pose",
    domain: Annotated[int, typer.Option(min=0, max=232, metavar="ID", help="ROS_DOMAIN_ID, with --ros2 rmw_zenoh")] = 0,
    namespace: Annotated[str, typer.Option(metavar="NAMESPACE", help="zenoh-bridge-ros2dds namespace, with --ros2 bridge_dds")] = "",
    frame: Annotated[str, typer.Option(metavar="X,Y,YAW", help="the tracker's frame in the path's: rotate by YAW (rad), then shift by X, Y (m)")] = "0,0,0",
    connect: Endpoints = [],
    listen: Endpoints = [],
    zenoh_config: Annotated[Optional[Path], typer.Option(help="Zenoh config file (JSON5)")] = None,
    duration: Annotated[Optional[float], typer.Option(help="stop after this many seconds (default: until Ctrl-C)")] = None,
    allow_insecure: AllowInsecure = False,
) -> None:
    """Publish a motion capture's rigid bodies as robot poses on Zenoh (our format or ROS 2 PoseStamped)."""
    from bridge.mocap import SYSTEMS, BodyMap, MocapError, MocapPublisher, read_frames, run_mocap
    from bridge.protocol import check_prefix
    from bridge.ros2.node import CONVENTIONS, RosGraph
    from bridge.session import SessionError, open_session, zenoh_config as make_config

    if system not in SYSTEMS:
        fail(2, f"--system {system}: expected one of {', '.join(SYSTEMS)}")
    if ros2 is not None and ros2 not in CONVENTIONS:
        fail(2, f"--ros2 {ros2}: expected one of {', '.join(CONVENTIONS)}")
    problems = check_prefix(prefix)
    if problems:
        fail(2, f"--prefix: {problems[0]}")
    mapped = []
    for name, robot in _pairs(bodies, "--body"):
        if not robot.isdigit():
            fail(2, f"--body {name}={robot}: the robot id must be a whole number")
        mapped.append(BodyMap(name, int(robot), topic.replace("{body}", name) if ros2 else None))
    settings = dict(_pairs(options, "--option"))
    if host:
        settings["hostname"] = host
    graph = RosGraph(ros2, domain, namespace, "platoon_mocap") if ros2 else None
    stop = threading.Event()
    stop_on_signals(stop)
    try:
        config = make_config(connect, listen, str(zenoh_config) if zenoh_config else None,
                             allow_insecure=allow_insecure)
        with open_session(config, "platoon mocap") as session:
            publisher = MocapPublisher(session, mapped, prefix, graph, _frame(frame))
            for body in mapped:
                print(f"mocap: body {body.body} -> robot {body.robot} on {publisher.where(body, prefix)}", flush=True)
            try:
                count = run_mocap(read_frames(system, settings, stop), publisher, duration)
            finally:
                publisher.close()
            print(f"mocap: {count} frames read", flush=True)
    except (MocapError, SessionError) as error:
        fail(2, str(error))


def register(app: typer.Typer) -> None:
    """Add ``platoon mocap``."""
    app.command("mocap")(mocap)
