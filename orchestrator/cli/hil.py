"""The hardware-in-the-loop commands of ``platoon``: ``m3pi-emulator``, ``m3pi-serial``, and the live
summary table a run prints. One module of the command line (orchestrator/cli/).

Both commands are long-running processes that stop on Ctrl-C or SIGTERM; the robot side always stops
its wheels before it exits.
"""

from __future__ import annotations

import math
import os
import signal
import threading
from pathlib import Path
from typing import TYPE_CHECKING, Annotated, Any, Optional

import typer

from orchestrator.cli.common import fail, load_config
from orchestrator.support.text import ms_text

if TYPE_CHECKING:  # imported where used: registering these commands must not slow every `platoon` start
    from rich.table import Table

Endpoints = Annotated[list[str], typer.Option(metavar="ENDPOINT", help="Zenoh endpoint, e.g. tcp/127.0.0.1:7447 (repeatable)")]
LabKeyOption = Annotated[Optional[Path], typer.Option("--lab-key", metavar="FILE", help="the lab key file the runs "
                                                     "share (default: $PLATOON_LAB_KEY, else ~/.config/platoon/lab.key, "
                                                     "made if missing; docs/hil.md, \"Who can start the robot\")")]
AllowInsecure = Annotated[bool, typer.Option("--allow-insecure", help="allow endpoints off this machine without TLS "
                                                                      "(docs/hil.md, \"A secure lab\")")]


def stop_on_signals(stop: threading.Event) -> None:
    """SIGINT and SIGTERM set ``stop``: the program's loop ends, stops the wheels, releases Zenoh.

    Not from the handler itself: Python runs it on the main thread between two bytecodes, which may be inside
    ``stop.wait()`` with the event's (non-reentrant) lock held, and ``stop.set()`` there waits for that lock
    forever (an emulator hung on Ctrl-C, then on every signal after it: tests/test_signal_stop.py). The
    handler writes a byte to a pipe, which takes no lock; a thread waiting on the pipe sets ``stop``."""
    read_end, write_end = os.pipe()

    def relay() -> None:
        os.read(read_end, 1)
        stop.set()

    def handler(signum: int, frame: object) -> None:
        try:
            os.write(write_end, b"\0")
        except OSError:  # the pipe full of earlier signals: ``stop`` is being set already
            pass

    os.set_blocking(write_end, False)
    threading.Thread(target=relay, name="signal-stop", daemon=True).start()
    for signum in (signal.SIGINT, signal.SIGTERM):
        signal.signal(signum, handler)



def robot_side_key(named: Any) -> Any:
    """The lab key a robot side checks the runs' commands with (``bridge.lab_key``), or exit 2 naming the file."""
    from bridge.lab_key import LabKeyError, load_lab_key

    try:
        return load_lab_key(named)
    except LabKeyError as error:
        fail(2, str(error))


def live_table(summary: dict[str, dict[str, Any]]) -> Table:
    """Pacing and link statistics of a live run, one row per live vehicle (fits 80 columns)."""
    from bridge.claim import describe_interference

    pacing = summary.get("pacing", {})
    title = (f"live: step jitter median {ms_text(pacing.get('jitter.median'))} ms, p99 {ms_text(pacing.get('jitter.p99'))} ms, "
             f"max {ms_text(pacing.get('jitter.max'))} ms; overruns {pacing.get('overruns', 0)} of {pacing.get('points', 0)}"
             + (f", behind by {ms_text(pacing['behind.total'])} ms in all (its stalls added up, each caught up after)"
                if pacing.get("overruns") and "behind.total" in pacing else ""))
    notes = ["trip: command sent -> first pose taken after the robot applied it (median/p99); "
             "age: of the pose each step used (median/max)"]
    headers = ("vehicle", "robot", "state", "cmds", "poses", "dropped", "trip ms", "age ms")
    rows = []
    for name, stats in summary.items():
        if name == "pacing":
            continue
        dropped = {k.split(".")[-1]: v for k, v in stats.items() if k.startswith("pose.dropped.") and v}
        if dropped:
            notes.append(f"{name} dropped: " + ", ".join(f"{reason} {count}" for reason, count in dropped.items()))
        refused = describe_interference(int(stats.get("command.foreign", 0)), int(stats.get("command.invalid", 0)),
                                        str(stats.get("command.foreign_claim", "")))
        if refused:
            notes.append(f"{name}: {refused}")
        if stats.get("command.sent") and not (stats.get("command.accepted") or stats.get("command.dropped")):
            notes.append(f"{name}: its robot side reported nothing back (a ROS 2 robot sends no status): how many "
                         "commands it received and its safety stops are not known here; its own log has them")
        if stats.get("command.safety_stops"):
            notes.append(f"{name}: robot-side safety stops {stats['command.safety_stops']} (no command for up to "
                         f"{ms_text(stats.get('command.longest_gap'))} ms, past the deadline: the run stalled)")
        trip = "-/-"  # a pose source that does not echo command numbers (a motion capture, ROS) measures none
        if stats.get("round_trip.count", 0):
            trip = f"{ms_text(stats.get('round_trip.median'))}/{ms_text(stats.get('round_trip.p99'))}"
        rows.append((
            name, str(stats.get("robot", "")), str(stats.get("state", "")), str(stats.get("command.sent", 0)),
            str(stats.get("pose.accepted", 0)), str(sum(dropped.values())),
            trip,
            f"{ms_text(stats.get('pose_age.median'))}/{ms_text(stats.get('pose_age.max'))}",
        ))
    from rich import box
    from rich.table import Table

    table = Table(title=title, title_justify="left", caption_justify="left", box=box.SIMPLE_HEAD, pad_edge=False,
                  collapse_padding=True)
    for index, header in enumerate(headers):  # every cell whole: the widths a row needs, no ellipsis
        width = max([len(header), *(len(row[index]) for row in rows)])
        table.add_column(header, justify="left" if header in ("vehicle", "state") else "right", min_width=width)
    for row in rows:
        table.add_row(*row)
    table.caption = "\n".join(notes)
    return table


def emulated_robots(config: Any, ids: list[int], truths: Any = None) -> list[Any]:
    """One ``RobotSpec`` per live vehicle of ``config`` (only robots ``ids`` if given), placed as the run starts it,
    each the config's m3pi unless ``truths`` (a ``bridge.robot_truth.TruthFile``) gives its robot its own physics."""
    from bridge.emulator import RobotSpec
    from bridge.protocol import RobotKeys
    from bridge.robot_truth import RobotTruth
    from fmus.model.dynamics import M3piDynamics

    from orchestrator.scenario.scenario import initial_states

    states = initial_states(config)
    robots = []
    for vehicle in config.live_vehicles():
        robot = config.robot_id(vehicle)
        if ids and robot not in ids:
            continue
        override = config.override(vehicle)
        x, y, heading, speed = states[vehicle - 1]
        m3pi = config.m3pi_of(vehicle)
        dynamics = M3piDynamics(override.k_v or config.platoon.k_v, m3pi.track, m3pi.wheel_speed_max,
                                m3pi.motor_time_constant, m3pi.wheel_gain_right, m3pi.wheel_gain_left,
                                m3pi.wheel_deadband)
        truth = truths.robot(robot) if truths is not None else RobotTruth()
        robots.append(RobotSpec(RobotKeys(override.prefix or config.hil.prefix, robot), x, y, heading, speed,
                                truth.dynamics(dynamics), truth))
    return robots


def emulated_links(config: Any, ids: list[int], convention: str | None) -> list[Any]:
    """The ``bridge.ros2.link.RosLink`` (or None) of each robot ``emulated_robots`` gives, in its order;
    ``convention`` (``--ros2``) replaces the config's for every robot with a ``[vehicles.K.ros2]`` table."""
    from dataclasses import replace

    from orchestrator.components.live import ros_link

    links = []
    for vehicle in config.live_vehicles():
        if ids and config.robot_id(vehicle) not in ids:
            continue
        link = ros_link(config, vehicle)
        if link is not None and convention is not None:
            link = replace(link, graph=replace(link.graph, convention=convention))
        links.append(link)
    return links


def emulator_endpoints(config: Any) -> tuple[list[str], list[str]]:
    """(listen, connect) that meet the live vehicles: listen where the run connects, connect where it listens."""
    listen, connect = [], []
    for vehicle in config.live_vehicles():
        override = config.override(vehicle)
        listen += [e for e in override.connect or () if e not in listen]
        connect += [e for e in override.listen or () if e not in connect]
    return listen, connect


def m3pi_emulator(
    config: Annotated[Path, typer.Option("--config", help="scenario whose live vehicles (endpoint = \"zenoh\") to emulate")],
    overrides: Annotated[list[str], typer.Option("--set", metavar="KEY=VALUE", help="override a config key, as for platoon run")] = [],
    ids: Annotated[list[int], typer.Option("--id", metavar="K", help="emulate only this robot id (repeatable; default: all)")] = [],
    robots_file: Annotated[Optional[Path], typer.Option("--robots", metavar="TRUTH.toml", help="each robot's own physics, "
                           "latencies and noise (docs/hil.md, \"Calibrating your robots\"); the run never reads it")] = None,
    rate: Annotated[float, typer.Option(metavar="HZ", help="poses per second (motion capture rate), Hz")] = 200.0,
    noise_position: Annotated[float, typer.Option(metavar="METRES", help="pose noise in m (standard deviation per axis; paper ~0.002 m)")] = 0.0,
    noise_heading: Annotated[float, typer.Option(metavar="DEGREES", help="heading noise in degrees, not radians as in configs (standard deviation; paper ~2 degrees = 0.035 rad)")] = 0.0,
    latency: Annotated[float, typer.Option(metavar="SECONDS", help="s from taking a pose to publishing it")] = 0.0,
    command_latency: Annotated[float, typer.Option(metavar="SECONDS", help="s from receiving a command to applying it (the radio)")] = 0.0,
    command_timeout: Annotated[float, typer.Option(metavar="SECONDS", help="s without a valid command before the wheels stop")] = 0.25,
    standing_start: Annotated[bool, typer.Option("--standing-start", help="start from rest, not at the config's initial speed")] = False,
    steady_radio: Annotated[bool, typer.Option("--steady-radio", help="count each command's latency from its send time "
                            "(deadline less the config's hil.command_validity), not from its arrival: this host's "
                            "delivery jitter does not reach the wheels (a test bench's choice, docs/hil.md)")] = False,
    seed: Annotated[Optional[int], typer.Option(help="noise seed (default: different every run)")] = None,
    listen: Endpoints = [],
    connect: Endpoints = [],
    zenoh_config: Annotated[Optional[Path], typer.Option(help="Zenoh config file (JSON5)")] = None,
    duration: Annotated[Optional[float], typer.Option(help="stop after this many seconds (default: until Ctrl-C)")] = None,
    ros2: Annotated[Optional[str], typer.Option("--ros2", metavar="CONVENTION", help="speak ROS 2 on the topics of "
                    "each [vehicles.K.ros2] table through rmw_zenoh or bridge_dds (default: the tables' convention)")] = None,
    allow_insecure: AllowInsecure = False,
    lab_key: LabKeyOption = None,
) -> None:
    """Emulate the live robots of a config and their motion capture on Zenoh (stands in for the m3pi)."""
    from bridge.emulator import EmulatorSettings, run_emulator
    from bridge.session import SessionError

    from bridge.robot_truth import TruthError, load_truth

    parsed, _ = load_config(config, overrides)
    try:
        truths = load_truth(robots_file) if robots_file is not None else None
    except TruthError as error:
        fail(2, str(error))
    robots = emulated_robots(parsed, ids, truths)
    if not robots:
        wanted = f" with robot id {', '.join(map(str, ids))}" if ids else ""
        fail(2, f"config {config}: no live vehicle{wanted} (set endpoint = \"zenoh\" on a [vehicles.K] table)")
    for name, value, unit in (("--rate", rate, "Hz"), ("--command-timeout", command_timeout, "s")):
        if not (math.isfinite(value) and value > 0.0):
            fail(2, f"{name} {value}: expected a finite number > 0 {unit}")
    for name, value, unit in (("--noise-position", noise_position, "m"), ("--noise-heading", noise_heading, "degrees"),
                              ("--latency", latency, "s"), ("--command-latency", command_latency, "s")):
        if not (math.isfinite(value) and value >= 0.0):
            fail(2, f"{name} {value}: expected a finite number >= 0 {unit}")
    if ros2 is not None and ros2 not in ("rmw_zenoh", "bridge_dds"):
        fail(2, f"--ros2 {ros2}: expected rmw_zenoh or bridge_dds")
    links = emulated_links(parsed, ids, ros2)
    if ros2 is not None and not any(links):
        fail(2, f"--ros2 {ros2}: config {config} has no [vehicles.K.ros2] table (pose_topic, command_topic) to speak on")
    make = None
    if any(links):
        from bridge.ros2.emulator import RosEmulator

        def make(robots: list, settings: Any, zenoh_config: Any) -> Any:
            return RosEmulator(robots, settings, zenoh_config, links)
    default_listen, default_connect = emulator_endpoints(parsed)
    settings = EmulatorSettings(rate, noise_position, math.radians(noise_heading), latency, command_latency,
                                command_timeout, not standing_start, seed, robot_side_key(lab_key or parsed.hil.lab_key),
                                parsed.hil.command_validity if steady_radio else None)
    stop = threading.Event()
    stop_on_signals(stop)
    try:
        run_emulator(robots, settings, connect or default_connect, listen or default_listen,
                     str(zenoh_config) if zenoh_config else None, duration, stop, make=make,
                     allow_insecure=allow_insecure or parsed.hil.allow_insecure)
    except SessionError as error:
        fail(2, str(error))


def m3pi_serial(
    port: Annotated[str, typer.Option("--port", metavar="DEV", help="serial device of the XBee, e.g. /dev/ttyUSB0")],
    robot: Annotated[int, typer.Option("--id", help="robot id whose wheel commands to forward")],
    prefix: Annotated[str, typer.Option(metavar="PREFIX", help="Zenoh key prefix")] = "platoon",
    connect: Endpoints = [],
    listen: Endpoints = [],
    zenoh_config: Annotated[Optional[Path], typer.Option(help="Zenoh config file (JSON5)")] = None,
    max_speed: Annotated[float, typer.Option(metavar="M/S", help="wheel speed (m/s) that speed byte 127 drives: measure it")] = 1.0,
    swap_motors: Annotated[bool, typer.Option("--swap-motors", help="M1 is the right motor (default: M1 left, M2 right)")] = False,
    invert_left: Annotated[bool, typer.Option("--invert-left", help="the left motor is wired backwards")] = False,
    invert_right: Annotated[bool, typer.Option("--invert-right", help="the right motor is wired backwards")] = False,
    baud: Annotated[int, typer.Option(min=1200, metavar="BAUD", help="serial speed of the XBee link")] = 115200,
    command_timeout: Annotated[float, typer.Option(metavar="SECONDS", help="s without a valid command before the motors stop")] = 0.25,
    allow_insecure: AllowInsecure = False,
    lab_key: LabKeyOption = None,
) -> None:
    """Forward one robot's wheel commands from Zenoh to a Pololu 3pi serial slave over an XBee."""
    from bridge.protocol import check_prefix
    from bridge.serial_endpoint import SerialEndpointError, SpeedScale, run_serial_endpoint
    from bridge.session import SessionError

    problems = check_prefix(prefix)
    if problems:
        fail(2, f"--prefix: {problems[0]}")
    if not (math.isfinite(max_speed) and max_speed > 0.0):
        fail(2, f"--max-speed {max_speed}: expected a finite speed > 0 (m/s at speed byte 127)")
    if not (math.isfinite(command_timeout) and command_timeout > 0.0):
        fail(2, f"--command-timeout {command_timeout}: expected a finite number of seconds > 0")
    scale = SpeedScale.from_options(max_speed=max_speed, swap_motors=swap_motors, invert_left=invert_left,
                                    invert_right=invert_right)
    stop = threading.Event()
    stop_on_signals(stop)
    try:
        run_serial_endpoint(port, robot, prefix=prefix, connect=connect, listen=listen,
                            zenoh_config_file=str(zenoh_config) if zenoh_config else None, scale=scale,
                            command_timeout=command_timeout, baud=baud, stop_event=stop,
                            allow_insecure=allow_insecure, lab_key=robot_side_key(lab_key))
    except (SerialEndpointError, SessionError, OSError, ValueError) as error:
        fail(2, str(error))


def register(app: typer.Typer) -> None:
    """Add the hardware-in-the-loop commands to ``platoon``."""
    app.command("m3pi-emulator")(m3pi_emulator)
    app.command("m3pi-serial")(m3pi_serial)
    from orchestrator.cli.hil_certs import hil_certs

    app.command("hil-certs")(hil_certs)
