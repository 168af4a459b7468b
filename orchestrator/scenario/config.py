"""Scenario configuration: TOML files, ``--set KEY=VALUE`` overrides, validation with clear errors.

Every key is documented in docs/config.md. Validation is pydantic in strict mode (a count must be an
integer, a law one of the known names), plus the cross-field rules a platoon needs (d* fits the
circle, disturbances name existing vehicles). A bad config raises ``ConfigError`` whose message is one
line naming the key, the value and what was expected.

Every number has a declared range, in one place: the annotated types below (``Positive``, ``Angle``,
...), which pydantic enforces and ``_explain`` quotes back (``platoon.k_v = inf: must be a finite
number >= 0.001 and <= 1000``). No float key accepts inf or NaN (``allow_inf_nan=False`` for all).
"""

from __future__ import annotations

import math
import tomllib
from pathlib import Path
from typing import Annotated, Any, Literal, Union, get_args, get_origin

import annotated_types
from pydantic import AfterValidator, BaseModel, ConfigDict, Field, ValidationError, model_validator

from bridge.protocol import DEFAULT_PREFIX, check_prefix
from fmus.model.dynamics import (M3PI_MOTOR_TIME_CONSTANT, M3PI_TRACK, M3PI_WHEEL_DEADBAND, M3PI_WHEEL_GAIN,
                                 M3PI_WHEEL_SPEED_MAX)
from fmus.model.guidance import SENSING_LAWS
from fmus.model.integrate import substep_count
from fmus.model.link import CAPACITY as LINK_CAPACITY
from fmus.model.link import LinkParameters, messages_held
from fmus.model.link import parameter_errors as link_parameter_errors
from fmus.model.robot_loop import COMMAND_CAPACITY, LATENCY_MAX, M3PI_COMMAND_LATENCY, M3PI_POSE_LATENCY
from orchestrator.support.suggest import did_you_mean

from .raw_config import (DEFAULT_COUNT, DEFAULT_STEP, DEFAULT_STOP_TIME, DEFAULT_TRACE_EVERY, ConfigError, apply_override,
                         read_config_text, step_count)
from .raw_config import parse_value  # noqa: F401  (re-exported: a --set value's parser, where it always was)
from .ros2_config import RunRos2, VehicleRos2
from .ros2_config import _Rule as _Ros2Rule


class _Strict(BaseModel):
    model_config = ConfigDict(extra="forbid", strict=True, frozen=True, allow_inf_nan=False)


class _Expected(ValueError):
    """A field validator's complaint: what the value must be (``_explain`` adds the key and the value)."""


# Ranges. A platoon lives on a ground plane: 1000 km is far beyond any scenario and keeps doubles at
# sub-micrometre resolution (ulp(1e6) = 1.2e-10 m), so lengths and coordinates stay within it.
LENGTH_MAX = 1e6  # m
# The smallest length, speed, gain or time constant: a millimetre, a millimetre per second, a speed
# loop of 1000 s. Below, nothing physical is left and the analysis and the models divide by ~0.
SMALL = 1e-3
SPEED_MAX = 1000.0  # m/s: three times the speed of sound, far above any vehicle
GAIN_MAX = 1000.0  # 1/s: a speed loop faster than 1 ms is not a vehicle (and needs substeps below 1 ms)
ANGLE_MAX = 2.0 * math.pi  # rad: one turn either way states every direction
PULSE_MAX = 1e6  # m/s² or m/s (PULSE_UNITS): a disturbance beyond this only produces overflow



class Unit(str):
    """The unit of a numeric key, printed with its range in an error ("<= 6.28319 rad"): configs use SI
    units and radians, and a message says which."""


class UnitNote(str):
    """The unit of a numeric key that depends on another key, said once after its range in an error."""


# Every float is finite (allow_inf_nan=False above); these add the range and the unit.
Positive = Annotated[float, Field(gt=0.0)]
Duration = Annotated[float, Field(gt=0.0), Unit("s")]
Length = Annotated[float, Field(ge=-LENGTH_MAX, le=LENGTH_MAX), Unit("m")]
PositiveLength = Annotated[float, Field(ge=SMALL, le=LENGTH_MAX), Unit("m")]
Speed = Annotated[float, Field(ge=SMALL, le=SPEED_MAX), Unit("m/s")]
Gain = Annotated[float, Field(ge=SMALL, le=GAIN_MAX), Unit("1/s")]
Angle = Annotated[float, Field(ge=-ANGLE_MAX, le=ANGLE_MAX), Unit("rad")]
PULSE_UNITS = {"lateral_acceleration": "m/s²", "speed": "m/s"}  # a disturbance's value, by its kind
Pulse = Annotated[float, Field(ge=-PULSE_MAX, le=PULSE_MAX),
                  UnitNote(", ".join(f'{unit} for kind = "{kind}"' for kind, unit in PULSE_UNITS.items()))]

# The run's name becomes a file name (runs/<name>-<time>.mcap): letters, digits (any script), and a
# few punctuation marks, starting with a letter or digit, so it can hold no path separator, no "..",
# no control character and no shell-unfriendly leading "-".
# The length is a separate constraint: "[...]{0,99}" in the pattern made pydantic-core's regex engine
# build 99 copies of the Unicode class \w, ~30 ms of every run's start-up (docs/performance.md).
NAME_PATTERN = r"^\w[\w .,+=@#()-]*$"
NAME_LENGTH_MAX = 100
NAME_RULE = "letters, digits, spaces and . , + = @ # ( ) - _, starting with a letter or digit, at most 100 characters"


def _clean_text(text: str) -> str:
    """Free text may span lines and hold tabs, but no NUL or other control character (they break file
    names, Zenoh endpoints, terminals and C strings further on), and must be encodable as UTF-8 (a
    command-line argument that was not UTF-8 arrives with lone surrogates, which no file can hold)."""
    try:
        text.encode("utf-8")
    except UnicodeEncodeError:
        raise _Expected("must be valid UTF-8 text") from None
    bad = [c for c in text if (ord(c) < 0x20 and c not in "\t\n\r") or ord(c) == 0x7F]
    if bad:
        raise _Expected(f"must be text without control characters (found {bad[0]!r})")
    return text


Text = Annotated[str, AfterValidator(_clean_text)]
Name = Annotated[str, Field(pattern=NAME_PATTERN, max_length=NAME_LENGTH_MAX)]

# RK4 alone is stable on dx/dt = -x/T for substeps h < 2.785 T (its real stability interval); coupled
# to the guidance through the speed chain it needs a margin: the paper's platoon at k_v = 1000 1/s
# diverged at h = 2.5 T and ran at h = 2 T (measured, docs/config.md).
RK4_STABILITY = 2.0

# Steps and substeps are counted in integers from float ratios: exact only up to 2**53.
COUNT_LIMIT = 2**53


class Simulation(_Strict):
    stop_time: Duration = Field(DEFAULT_STOP_TIME, description="simulated time, s")
    step: Duration = Field(DEFAULT_STEP, description="communication step, s (at most stop_time)")
    master: Literal["jacobi", "gauss-seidel"] = "jacobi"
    coupling: Literal["extrapolate", "hold"] = "extrapolate"
    max_substep: Duration = Field(0.01, description="longest RK4 substep inside an FMU, s")
    trace_every: int = Field(DEFAULT_TRACE_EVERY, ge=1, description="record every K-th communication point (at most the step count)")
    fmus: Literal["native", "python"] | None = Field(
        None, description="FMUs to step: native (C, no Python on the host) or python (pythonfmu); "
                          "default native where a C compiler can build them (orchestrator/components/kinds.py)")


class PathConfig(_Strict):
    kind: Literal["circle", "line"] = "circle"
    radius: PositiveLength = 50.0
    center: list[Length] = Field(default_factory=lambda: [0.0, 0.0], min_length=2, max_length=2)
    heading: Angle = 0.0
    direction: Literal["ccw", "cw"] = "ccw"


Track = Annotated[float, Field(ge=SMALL, le=10.0), Unit("m")]
WheelSpeed = Annotated[float, Field(ge=SMALL, le=100.0), Unit("m/s")]
MotorLag = Annotated[float, Field(ge=SMALL, le=100.0), Unit("s")]
# A wheel that turns at a tenth of its command, or ten times it, is a broken motor, not one to calibrate.
WheelGain = Annotated[float, Field(ge=0.1, le=10.0)]
Deadband = Annotated[float, Field(ge=0.0, le=100.0), Unit("m/s")]
Latency = Annotated[float, Field(ge=0.0, le=LATENCY_MAX), Unit("s")]


class M3pi(_Strict):
    """The m3pi robots' constants (docs/model.md): the nominal robot by default; a calibrated config sets the
    gains, dead-band and latencies `platoon calibrate` identifies, here or per vehicle ([vehicles.N.m3pi])."""

    track: Track = Field(M3PI_TRACK, description="m")
    wheel_speed_max: WheelSpeed = Field(M3PI_WHEEL_SPEED_MAX, description="m/s")
    motor_time_constant: MotorLag = Field(M3PI_MOTOR_TIME_CONSTANT, description="s")
    wheel_gain_right: WheelGain = Field(M3PI_WHEEL_GAIN, description="right wheel speed per commanded speed")
    wheel_gain_left: WheelGain = Field(M3PI_WHEEL_GAIN, description="left wheel speed per commanded speed")
    wheel_deadband: Deadband = Field(M3PI_WHEEL_DEADBAND, description="m/s: a smaller command does not turn a wheel")
    command_latency: Latency = Field(M3PI_COMMAND_LATENCY, description="s: a command acts this long after it is sent")
    pose_latency: Latency = Field(M3PI_POSE_LATENCY, description="s: a pose is this much older than its stamp")

    @property
    def samples(self) -> bool:
        """A robot with latencies: the live run's sampled loop (fmus.model.robot_loop), not the continuous model."""
        return self.command_latency > 0.0 or self.pose_latency > 0.0

    def parameters(self) -> dict[str, float]:
        """The Vehicle FMU's ``m3pi.*`` parameters of these constants."""
        return {f"m3pi.{key}": value for key, value in self.model_dump().items()}


class M3piOverride(_Strict):
    """``[vehicles.N.m3pi]``: the constants of vehicle N's robot that differ from ``[m3pi]`` (each robot is its own)."""

    track: Track | None = None
    wheel_speed_max: WheelSpeed | None = None
    motor_time_constant: MotorLag | None = None
    wheel_gain_right: WheelGain | None = None
    wheel_gain_left: WheelGain | None = None
    wheel_deadband: Deadband | None = None
    command_latency: Latency | None = None
    pose_latency: Latency | None = None


Law = Literal["sine", "regular"]
DynamicsKind = Literal["kinematic", "m3pi"]
# The speed laws (fmus.model.guidance.SPEED_LAWS; docs/model.md, section 11): the paper's, a constant-time-gap
# ACC, Ploeg's CACC adapted to the first-order speed loop.
SpeedLawName = Literal["paper", "acc", "cacc"]
# A time gap beyond 100 s is no platoon; below 1 ms the cacc pole -1/h is beyond any substep (the stiffness
# check below names it).
TimeGap = Annotated[float, Field(ge=SMALL, le=100.0), Unit("s")]
GapLength = Annotated[float, Field(ge=0.0, le=LENGTH_MAX), Unit("m")]


class Platoon(_Strict):
    count: int = Field(DEFAULT_COUNT, ge=1, le=10000)
    law: Law = "sine"
    d_star: PositiveLength = Field(75.0, description="m; on a circle less than 2 path.radius")
    k_v: Gain = 0.5
    speed: Speed = Field(25.0, description="V_c, the last vehicle's commanded speed")
    dynamics: DynamicsKind = "kinematic"
    speed_law: SpeedLawName = Field("paper", description="paper (V d*/d), acc (constant time gap) or cacc (Ploeg)")
    time_gap: TimeGap = Field(2.0, description="h of acc and cacc: desired gap standstill_gap + h V, s")
    standstill_gap: GapLength | None = Field(None, description="r of acc and cacc, m (default d_star - time_gap speed)")
    cacc_gain: Gain = Field(0.2, description="k_p of cacc (Ploeg et al. 2011), 1/s")
    speed_max: Speed | None = Field(None, description="m/s: a kinematic vehicle's speed limit (default: none)")

    @property
    def resolved_standstill_gap(self) -> float:
        """r: as given, or the one that makes the acc/cacc equilibrium gap d* at V_c (d* - h V_c)."""
        if self.standstill_gap is not None:
            return self.standstill_gap
        return self.d_star - self.time_gap * self.speed


class Validity(_Strict):
    """Where a run stops being the model's (orchestrator/analysis/validity.py; docs/model.md, section 12): it
    keeps running, and says so in its summary, its log, `platoon report --json` and a sweep's row."""

    min_gap: GapLength | None = Field(None, description="m: a gap at or below it is a collision (default: a vehicle's "
                                      "size, 4.5 m or the m3pi's 0.095 m, at most half the equilibrium gap)")
    max_speed: Speed | None = Field(None, description="m/s: a faster vehicle has left the model (default: 3 V_c for "
                                    "kinematic vehicles; an m3pi is bounded by its wheels)")


class Initial(_Strict):
    """Default placement: on the path behind the target, spaced by the chord d*, then perturbed."""

    radial_offset: Length = Field(0.0, description="vehicle 1 moved this far off the path (outward), m")
    heading_error: Angle = Field(0.0, description="added to vehicle 1's heading, rad")
    speed_factor: Annotated[float, Field(ge=SMALL, le=10.0)] = Field(1.0, description="every vehicle starts at this fraction of V_c")


class VehicleState(_Strict):
    x: Length
    y: Length
    heading: Angle
    speed: Speed


class VehicleOverride(_Strict):
    law: Law | None = None
    speed_law: SpeedLawName | None = None
    k_v: Gain | None = None
    dynamics: DynamicsKind | None = None
    initial: VehicleState | None = None
    m3pi: M3piOverride | None = Field(None, description="this vehicle's robot constants, over [m3pi]")
    # Hardware in the loop (docs/hil.md): "zenoh" makes this vehicle a live m3pi robot on Zenoh; the keys
    # after it say where the robot is, and are ignored with "fmu".
    endpoint: Literal["fmu", "zenoh", "remote"] = "fmu"
    # "remote" (docs/remote.md): the Vehicle FMU runs in a `platoon serve` named ``server`` (default
    # vehicle<K>), reached through connect/listen/zenoh_config, under prefix
    server: str | None = Field(None, description="the remote vehicle's `platoon serve --name` (default vehicle<K>)")
    robot: int | None = Field(None, ge=0, le=2**31 - 1, description="robot id on Zenoh (default: the vehicle number)")
    prefix: str | None = Field(None, description="key prefix (default hil.prefix)")
    connect: list[Text] | None = Field(None, description="Zenoh endpoints to connect to, e.g. tcp/127.0.0.1:7447")
    listen: list[Text] | None = Field(None, description="Zenoh endpoints to listen on")
    zenoh_config: Text | None = Field(None, description="Zenoh config file (JSON5): TLS, access control, ...")
    ros2: VehicleRos2 | None = Field(None, description="pose and/or commands on ROS 2 topics (docs/hil.md)")

    @model_validator(mode="after")
    def _prefix_is_a_key(self) -> "VehicleOverride":
        # robot, prefix, connect, listen and zenoh_config only act with endpoint = "zenoh"; they may stay
        # when a run sets endpoint = "fmu" (the same platoon all simulated, for comparison)
        for key in ("prefix", "server"):
            value = getattr(self, key)
            problems = check_prefix(value) if value is not None else []
            if problems:
                raise _rule(key, value, problems[0])
        return self


class Remote(_Strict):
    """Remote vehicles (docs/remote.md): how patient the run is with their servers."""

    step_timeout: Annotated[float, Unit("s")] = Field(2.0, gt=0.0, le=600.0, description="s to wait for a server's reply "
                                                                                       "to one call: then the run fails")
    connect_timeout: Annotated[float, Unit("s")] = Field(10.0, gt=0.0, le=600.0, description="s to wait for each server "
                                                                                          "at the start")


class Hil(_Strict):
    """Hardware in the loop: shared by every live vehicle of the run (docs/hil.md)."""

    prefix: str = Field(DEFAULT_PREFIX, description="Zenoh key prefix: <prefix>/m3pi/<id>/...")
    pose_timeout: Annotated[float, Unit("s")] = Field(0.5, gt=0.0, le=5.0, description="s without a valid pose: the robot is lost")
    connect_timeout: Annotated[float, Unit("s")] = Field(10.0, gt=0.0, le=600.0, description="s to wait for each robot at the start")
    command_validity: Annotated[float, Unit("s")] = Field(0.1, gt=0.0, le=5.0, description="s: a command's deadline after it is sent")
    max_pose_age: Annotated[float, Unit("s")] = Field(0.25, gt=0.0, le=5.0, description="s: an older pose is dropped as late")
    allow_insecure: bool = Field(False, description="allow Zenoh endpoints off this machine without TLS "
                                                    "(docs/hil.md, \"A secure lab\")")
    lab_key: Text | None = Field(None, description="the lab key file runs and robot sides share (default: "
                                                   "$PLATOON_LAB_KEY or ~/.config/platoon/lab.key; docs/hil.md)")

    @model_validator(mode="after")
    def _prefix_is_a_key(self) -> "Hil":
        problems = check_prefix(self.prefix)
        if problems:
            raise _rule("prefix", self.prefix, problems[0])
        return self


TARGET_VEHICLE = 0  # a disturbance's ``vehicle`` naming the virtual target, the platoon's head


class Disturbance(_Strict):
    # 1 .. platoon.count, or 0: the virtual target (a speed push only: the head's speed, prescribed)
    vehicle: int = Field(ge=TARGET_VEHICLE)
    kind: Literal["lateral_acceleration", "speed"]
    start: Annotated[float, Field(ge=0.0), Unit("s")]
    duration: Duration
    value: Pulse = Field(description="m/s² for kind lateral_acceleration, m/s for kind speed")
    # 0: a rectangular pulse of height value; > 0: value * sin(frequency (t - start)) over the same window,
    # a sinusoid to measure the speed chain's gain at one frequency (docs/model.md, section 12)
    frequency: Annotated[float, Field(ge=0.0, le=1e4), Unit("rad/s")] = 0.0

    @property
    def unit(self) -> str:
        """The unit of ``value``: m/s² for a lateral acceleration, m/s for a speed."""
        return PULSE_UNITS[self.kind]

    @property
    def on_target(self) -> bool:
        """A push on the virtual target (vehicle 0), not on a vehicle."""
        return self.vehicle == TARGET_VEHICLE

    def what(self) -> str:
        """The pulse's size and target in words, with its unit: "+5 m/s speed on vehicle 2" ("on the target")."""
        where = "the target" if self.on_target else f"vehicle {self.vehicle}"
        return f"{self.value:+g} {self.unit} {self.kind.replace('_', ' ')} on {where}"

    def text(self) -> str:
        """The whole pulse in words: "+5 m/s speed on vehicle 2 at 30 s for 1 s"."""
        shape = f", a sinusoid of {self.frequency:g} rad/s," if self.frequency > 0.0 else ""
        return f"{self.what()}{shape} at {self.start:g} s for {self.duration:g} s"


LinkTime = Annotated[float, Field(ge=0.0, le=3600.0), Unit("s")]
LINK_DIRECTIONS = ("backward", "forward")


class LinkKeys(_Strict):
    """One link's settings (docs/links.md); a key left out comes from the wider table."""

    delay: LinkTime | None = Field(None, description="s from a message's output_time to its arrival")
    jitter: LinkTime | None = Field(None, description="s: each message's extra delay is uniform in [0, jitter]")
    period: LinkTime | None = Field(None, description="s between beacons; 0: every communication step")
    loss: Annotated[float, Field(ge=0.0, le=1.0)] | None = Field(None, description="probability a message is lost")
    burst: Annotated[float, Field(ge=1.0, le=1e6)] | None = Field(
        None, description="mean burst length in messages; > 1: Gilbert-Elliott losses with the same mean loss")
    seed: int | None = Field(None, ge=0, le=2**31 - 1, description="seed of every link's random stream")


class VehicleLinks(_Strict):
    """The two links between vehicle N and the component ahead of it (the target for vehicle 1)."""

    backward: LinkKeys = LinkKeys()
    forward: LinkKeys = LinkKeys()


class Links(LinkKeys):
    """``[links]``: every link; ``[links.backward]``, ``[links.forward]``: one direction;
    ``[links.vehicles.N.backward]`` / ``.forward``: the links of vehicle N. The narrowest wins."""

    backward: LinkKeys = LinkKeys()
    forward: LinkKeys = LinkKeys()
    vehicles: dict[str, VehicleLinks] = Field(default_factory=dict)


def _link_layers(links: Links, direction: str, vehicle: int) -> list[LinkKeys]:
    """The tables that may set a key of one link, narrowest first."""
    own = links.vehicles.get(str(vehicle))
    layers = [getattr(own, direction)] if own is not None else []
    return layers + [getattr(links, direction), links]


def link_stream(direction: str, vehicle: int) -> int:
    """A link's own stream of the seed: 2 (N - 1) for vehicle N's backward link, + 1 for its forward one."""
    return 2 * (vehicle - 1) + LINK_DIRECTIONS.index(direction)


def resolve_link(links: Links, direction: str, vehicle: int) -> LinkParameters:
    """The settings of vehicle ``vehicle``'s ``direction`` link: each key from the narrowest table that
    sets it, else the perfect link's."""
    layers = _link_layers(links, direction, vehicle)
    default = LinkParameters()
    values = {key: next((getattr(t, key) for t in layers if getattr(t, key) is not None), getattr(default, key))
              for key in LinkKeys.model_fields}
    return LinkParameters(**values, stream=link_stream(direction, vehicle))


class Config(_Strict):
    name: Name = "scenario"
    description: Text = ""
    simulation: Simulation = Simulation()
    path: PathConfig = PathConfig()
    platoon: Platoon = Platoon()
    initial: Initial = Initial()
    m3pi: M3pi = M3pi()
    disturbance: list[Disturbance] = Field(default_factory=list)
    vehicles: dict[str, VehicleOverride] = Field(default_factory=dict)
    hil: Hil = Hil()
    remote: Remote = Remote()
    ros2: RunRos2 = RunRos2()
    links: Links = Links()
    validity: Validity = Validity()

    @model_validator(mode="after")
    def _platoon_rules(self) -> "Config":
        count = self.platoon.count
        if self.path.kind == "circle" and self.platoon.d_star >= 2.0 * self.path.radius:
            # d* = 2R puts each vehicle diametrically opposite its target: alpha = sqrt(1 - (d*/2R)^2) = 0,
            # the gap no longer responds to a speed difference and the equilibrium is degenerate (the
            # analysis divides by alpha; the paper's eigenvalue -V_c alpha/d* is 0)
            raise _rule("platoon.d_star", self.platoon.d_star, f"less than 2 * path.radius = {2.0 * self.path.radius} "
                        "(a chord of the circle shorter than its diameter: at d* = 2R the equilibrium is degenerate)")
        for index, item in enumerate(self.disturbance):
            if item.vehicle > count:
                raise _rule(f"disturbance[{index}].vehicle", item.vehicle, f"a vehicle number from 1 to platoon.count = {count} "
                            "(or 0, the virtual target)")
            if item.on_target and item.kind != "speed":
                raise _rule(f"disturbance[{index}].kind", item.kind, '"speed" on vehicle 0 (the virtual target has no '
                            'guidance to push sideways: push vehicle 1 instead)')
        for key, vehicle in self.vehicles.items():
            if not key.isdigit() or key != str(int(key)) or not 1 <= int(key) <= count:
                raise _rule(f"vehicles.{key}", key, f"a vehicle number from 1 to platoon.count = {count}")
            if vehicle.endpoint == "zenoh" and (vehicle.dynamics or self.platoon.dynamics) != "m3pi":
                raise _rule(f"vehicles.{key}.endpoint", "zenoh", 'm3pi dynamics, since a live robot is an m3pi: set '
                            f'platoon.dynamics = "m3pi" (or vehicles.{key}.dynamics)')
        robots = [(v.prefix or self.hil.prefix, self.robot_id(int(k))) for k, v in self.vehicles.items()
                  if v.endpoint == "zenoh"]
        if len(set(robots)) != len(robots):
            raise _rule("vehicles", [f"{p}/m3pi/{r}" for p, r in robots], "one live vehicle per robot (prefix and id)")
        sim = self.simulation
        if sim.step > sim.stop_time:
            raise _rule("simulation.step", sim.step, f"at most simulation.stop_time = {sim.stop_time}")
        steps, substeps = sim.stop_time / sim.step, max(1.0, sim.step / sim.max_substep)  # floats: may be inf
        if steps * substeps > COUNT_LIMIT:  # no option lifts this one (orchestrator/scenario/limits.py: the adjustable ones)
            raise _RuleError("simulation", None, "", message=(
                f"simulation: {steps:.3g} steps (stop_time / step) x {substeps:.3g} RK4 substeps each (step / "
                f"max_substep) = {steps * substeps:.3g} substeps per FMU: expected at most 2**53 = {COUNT_LIMIT:.3g} "
                "(beyond it step counts are not exact in double precision; no option lifts this)"))
        self._check_speed_laws()
        if self.platoon.speed_max is not None and self.platoon.speed_max < self.platoon.speed:
            raise _rule("platoon.speed_max", self.platoon.speed_max, f"at least platoon.speed = {self.platoon.speed:g} "
                        "m/s (a limit below the cruise speed keeps the platoon from ever reaching it)")
        self._check_robots()
        self._check_stiffness()
        self._check_links()
        if sim.trace_every > self.steps:
            raise _rule("simulation.trace_every", sim.trace_every, f"at most the run's {self.steps} steps "
                        "(stop_time / step), so that a point after t = 0 is recorded")
        return self

    def speed_law_of(self, vehicle: int) -> str:
        """Vehicle ``vehicle``'s speed law: its [vehicles.K] override, else platoon.speed_law."""
        return self.override(vehicle).speed_law or self.platoon.speed_law

    def header_text(self) -> str:
        """The laws, then the imperfect links if any: what a run's header says of the platoon."""
        links = self.links_text()
        return f"{self.laws_text()}, {links}" if links else self.laws_text()

    def links_text(self) -> str:
        """The run's imperfect links in a few words, "" when every link is perfect (run headers and the
        trace's first log line, beside the laws): "8 imperfect links (delay 0.1-0.12 s, 10% lost, beacons
        every 0.1 s on 4)", so that a lossy run's header does not read as a perfect-link run's."""
        links = [self.resolve_link(direction, vehicle) for direction, vehicle in self.linked()]
        if not links:
            return ""

        def span(values: list[float], unit: str = " s", form: str = "g") -> str:
            low, high = min(values), max(values)
            return f"{low:{form}}{unit}" if low == high else f"{low:{form}}-{high:{form}}{unit}"

        parts = []
        if any(link.delay + link.jitter > 0.0 for link in links):
            parts.append("delay " + span([link.delay for link in links] + [link.delay + link.jitter for link in links]))
        if any(link.loss > 0.0 for link in links):
            parts.append(span([link.loss for link in links], "", ".0%") + " lost")
        beacons = [link.period for link in links if link.period > 0.0]
        if beacons:
            parts.append("beacons every " + span(beacons) + ("" if len(beacons) == len(links) else f" on {len(beacons)}"))
        return f"{len(links)} imperfect link{'s' if len(links) > 1 else ''} ({', '.join(parts)})"

    def laws_text(self) -> str:
        """The guidance law and, when not the paper's alone, the speed laws: "sine law", "sine law, acc
        speed law", "sine law, speed laws paper (1), acc (2-4)" (run headers and the trace's first log line)."""
        laws = [self.speed_law_of(i) for i in range(1, self.platoon.count + 1)]
        text = f"{self.platoon.law} law"
        if set(laws) == {"paper"}:
            return text
        if len(set(laws)) == 1:
            return f"{text}, {laws[0]} speed law"
        runs: list[tuple[str, int, int]] = []  # (law, first vehicle, last vehicle)
        for vehicle, law in enumerate(laws, start=1):
            if runs and runs[-1][0] == law:
                runs[-1] = (law, runs[-1][1], vehicle)
            else:
                runs.append((law, vehicle, vehicle))
        parts = [f"{law} ({first})" if first == last else f"{law} ({first}-{last})" for law, first, last in runs]
        return f"{text}, speed laws {', '.join(parts)}"

    def sensing_vehicles(self) -> list[int]:
        """Numbers of the vehicles whose speed law reads the on-board sensor (acc, cacc), front to back."""
        return [i for i in range(1, self.platoon.count + 1) if self.speed_law_of(i) in SENSING_LAWS]

    def _check_speed_laws(self) -> None:
        """acc and cacc need a standstill gap r >= 0; the default r = d* - h V_c is negative for h > d*/V_c.

        Under the paper's law vehicle i's gap is regulated by the component ahead (it reads its follower's
        gap); under acc and cacc by vehicle i itself. A paper vehicle right behind an acc or cacc one would
        have its gap regulated by no one (it drifts: measured 91 m instead of 75 m), so it is refused.
        """
        p = self.platoon
        sensing = self.sensing_vehicles()
        for index in range(2, p.count + 1):
            if index - 1 in sensing and index not in sensing:
                key = f"vehicles.{index}.speed_law" if self.override(index).speed_law else "platoon.speed_law"
                raise _rule(key, self.speed_law_of(index), f"acc or cacc behind vehicle {index - 1}, whose "
                            f"{self.speed_law_of(index - 1)} law does not read its follower's gap: a paper vehicle's "
                            "gap is regulated by the vehicle ahead, so behind an acc or cacc one it would drift")
        if p.standstill_gap is None and sensing and p.resolved_standstill_gap < 0.0:
            raise _rule("platoon.time_gap", p.time_gap, f"at most platoon.d_star / platoon.speed = {p.d_star / p.speed:g} s "
                        f"under acc or cacc, or an explicit platoon.standstill_gap >= 0 (the default standstill gap "
                        f"d_star - time_gap * speed = {p.resolved_standstill_gap:g} m would be negative)")

    def _check_robots(self) -> None:
        """Each m3pi's dead-band lies below its wheel speed limit: a command is clipped to the limit, so a
        dead-band at or above it would keep the wheels still whatever the run commands. Its latencies may be any
        fraction of the step (the robot loop is exact there: fmus.model.robot_loop), but the commands they keep in
        flight must fit the robot's ring (COMMAND_CAPACITY)."""
        for vehicle in self.m3pi_vehicles():
            m3pi = self.m3pi_of(vehicle)
            if m3pi.wheel_deadband >= m3pi.wheel_speed_max:
                raise _rule(self.m3pi_key(vehicle, "wheel_deadband"), m3pi.wheel_deadband,
                            f"below vehicle {vehicle}'s wheel_speed_max = {m3pi.wheel_speed_max:g} m/s (a dead-band at "
                            "or above the limit keeps the wheels still whatever the run commands)")
            delay, step = m3pi.command_latency + m3pi.pose_latency, self.simulation.step
            if math.ceil(delay / step) + 1 > COMMAND_CAPACITY:
                raise _RuleError("m3pi", None, "", message=(
                    f"vehicle {vehicle}: command_latency + pose_latency = {delay:g} s spans {math.ceil(delay / step) + 1} "
                    f"commands in flight at simulation.step = {step:g} s; a robot holds at most {COMMAND_CAPACITY} "
                    "(a latency of a few tens of ms is a real radio; or lengthen the step)"))

    def _law_lags(self) -> list[tuple[str, float]]:
        """The fastest time constant each sensing law adds (1 / the largest |pole| of its loop, docs/model.md
        section 11): cacc's poles are -1/h and -k_p; acc's are the roots of h s^2 + k_v h s + k_v."""
        p, lags = self.platoon, []
        for index in self.sensing_vehicles():
            k_v = self.override(index).k_v or p.k_v
            if self.speed_law_of(index) == "cacc":
                lags.append(("platoon.time_gap", min(p.time_gap, 1.0 / p.cacc_gain)))
                continue
            a, b, c = p.time_gap, k_v * p.time_gap, k_v
            disc = b * b - 4.0 * a * c
            fastest = math.sqrt(c / a) if disc < 0.0 else (b + math.sqrt(disc)) / (2.0 * a)
            lags.append(("platoon.time_gap", 1.0 / fastest))
        return lags

    def _check_stiffness(self) -> None:
        """Every first-order lag must be resolved by the RK4 substep, or the integration blows up.

        RK4 on dx/dt = -x/T needs h/T below RK4_STABILITY; beyond it the speed loop (T = 1/k_v) or an
        m3pi motor (T = motor_time_constant) diverges within a few steps, and the run then fails with a
        NaN in whichever component reads it first, often not the one at fault. ``h`` is the substep the
        FMUs take: step / ceil(step / max_substep).
        """
        sim = self.simulation
        h = sim.step / substep_count(sim.step, sim.max_substep)
        lags = [(f"vehicles.{key}.k_v" if v.k_v is not None else "platoon.k_v", 1.0 / (v.k_v or self.platoon.k_v))
                for key, v in self.vehicles.items()] + [("platoon.k_v", 1.0 / self.platoon.k_v)] + self._law_lags()
        lags += [(self.m3pi_key(i, "motor_time_constant"), self.m3pi_of(i).motor_time_constant)
                 for i in self.m3pi_vehicles()]
        key, lag = min(lags, key=lambda item: item[1])
        if h > RK4_STABILITY * lag:
            raise _rule("simulation.max_substep", sim.max_substep,
                        f"RK4 substeps of at most {RK4_STABILITY:g} x the fastest lag, here {key} (time constant "
                        f"{lag:g} s): max_substep <= {RK4_STABILITY * lag:.3g} s (the substep is now {h:.3g} s; "
                        "beyond it the integration diverges)")

    def _check_links(self) -> None:
        """Links name existing vehicles, their losses can be bursty as asked, and none holds more
        messages than a Link FMU can (fmus.model.link.CAPACITY)."""
        count = self.platoon.count
        for key in self.links.vehicles:
            if not key.isdigit() or key != str(int(key)) or not 1 <= int(key) <= count:
                raise _rule(f"links.vehicles.{key}", key, f"a vehicle number from 1 to platoon.count = {count}")
        if self.links == Links():
            return  # no link: nothing to check for any of the vehicles
        for vehicle in range(1, count + 1):
            for direction in LINK_DIRECTIONS:
                link = self.resolve_link(direction, vehicle)
                where = f"links (vehicle {vehicle}'s {direction} link)"
                errors = link_parameter_errors(link)
                if errors:
                    raise _RuleError("links", None, "", message=f"{where}: {errors[0]}")
                held = messages_held(link, self.simulation.step)
                if held > LINK_CAPACITY:
                    raise _RuleError("links", None, "", message=(
                        f"{where}: delay + jitter = {link.delay + link.jitter:g} s spans up to {held} messages at "
                        f"step {self.simulation.step:g} s and period {link.period:g} s; a link holds at most "
                        f"{LINK_CAPACITY} (shorten the delay, or send beacons less often: links.period)"))

    def linked(self) -> list[tuple[str, int]]:
        """The (direction, vehicle) pairs whose link is not perfect: the run's Link components."""
        if self.links == Links():
            return []
        return [(direction, vehicle) for vehicle in range(1, self.platoon.count + 1) for direction in LINK_DIRECTIONS
                if not self.resolve_link(direction, vehicle).perfect]

    def resolve_link(self, direction: str, vehicle: int) -> LinkParameters:
        """The settings of vehicle ``vehicle``'s ``direction`` ("backward": from the component ahead to
        it; "forward": from it to the component ahead) link; perfect when no table sets a key."""
        return resolve_link(self.links, direction, vehicle)

    @property
    def steps(self) -> int:
        """Number of communication steps of this run."""
        return step_count(self.simulation.stop_time, self.simulation.step)

    def override(self, vehicle: int) -> VehicleOverride:
        return self.vehicles.get(str(vehicle), VehicleOverride())

    def dynamics_of(self, vehicle: int) -> str:
        """Vehicle ``vehicle``'s dynamics: its [vehicles.K] override, else platoon.dynamics."""
        return self.override(vehicle).dynamics or self.platoon.dynamics

    def m3pi_of(self, vehicle: int) -> M3pi:
        """Vehicle ``vehicle``'s robot constants: [m3pi], with its [vehicles.K.m3pi] keys over them."""
        own = self.override(vehicle).m3pi
        if own is None:
            return self.m3pi
        return self.m3pi.model_copy(update=own.model_dump(exclude_none=True))

    def m3pi_key(self, vehicle: int, key: str) -> str:
        """Where vehicle ``vehicle``'s m3pi ``key`` comes from, for an error: vehicles.K.m3pi.key or m3pi.key."""
        own = self.override(vehicle).m3pi
        return f"vehicles.{vehicle}.m3pi.{key}" if own is not None and getattr(own, key) is not None else f"m3pi.{key}"

    def m3pi_vehicles(self) -> list[int]:
        """The vehicles that are m3pi robots, front to back."""
        return [i for i in range(1, self.platoon.count + 1) if self.dynamics_of(i) == "m3pi"]

    def named_files(self) -> list[Path]:
        """The files this config names (``FILE_KEYS`` of [vehicles.K]): inputs of the run, like the config."""
        return [Path(value) for table in self.vehicles.values() for key in FILE_KEYS
                if (value := getattr(table, key, None))]

    def live_vehicles(self) -> list[int]:
        """Numbers of the vehicles that are live robots, front to back."""
        return sorted(int(k) for k, v in self.vehicles.items() if v.endpoint == "zenoh")

    def remote_vehicles(self) -> list[int]:
        """Numbers of the vehicles whose FMU runs in a `platoon serve` elsewhere, front to back."""
        return sorted(int(k) for k, v in self.vehicles.items() if v.endpoint == "remote")

    def robot_id(self, vehicle: int) -> int:
        robot = self.override(vehicle).robot
        return vehicle if robot is None else robot


class _RuleError(ValueError):
    def __init__(self, key: str, value: Any, expected: str, message: str | None = None) -> None:
        super().__init__(message or f"{key} = {value!r}: expected {expected}")
        self.key, self.value, self.expected = key, value, expected


def _rule(key: str, value: Any, expected: str) -> _RuleError:
    return _RuleError(key, value, expected)


def _key_of(loc: tuple[Any, ...]) -> str:
    key = ""
    for part in loc:
        if isinstance(part, int):
            key += f"[{part}]"
        else:
            key += ("." if key else "") + str(part)
    return key


_RANGE_ERRORS = {"finite_number", "greater_than", "greater_than_equal", "less_than", "less_than_equal"}
_BOUND_WORDS = (("gt", ">"), ("ge", ">="), ("lt", "<"), ("le", "<="))


def _field_at(loc: tuple[Any, ...]) -> tuple[Any, list[Any]]:
    """(type, constraint objects) of the key at pydantic location ``loc``, from the models' declarations."""
    annotation: Any = Config
    metadata: list[Any] = []
    for part in loc:
        annotation, metadata = _unwrap(annotation)
        origin = get_origin(annotation)
        if isinstance(annotation, type) and issubclass(annotation, BaseModel) and part in annotation.model_fields:
            info = annotation.model_fields[part]
            annotation, metadata = info.annotation, list(info.metadata)
        elif origin in (list, dict):
            annotation, metadata = get_args(annotation)[-1], []
        else:
            break
    annotation, more = _unwrap(annotation)
    return annotation, metadata + more


def _unwrap(annotation: Any) -> tuple[Any, list[Any]]:
    """Strip ``X | None`` and ``Annotated[X, ...]``, collecting the annotated constraints."""
    metadata: list[Any] = []
    while True:
        if get_origin(annotation) is Union or type(annotation).__name__ == "UnionType":
            annotation = next(a for a in get_args(annotation) if a is not type(None))
        elif get_origin(annotation) is Annotated:
            annotation, *extra = get_args(annotation)
            for item in extra:  # a Field(...) in Annotated carries its constraints as metadata
                metadata += list(getattr(item, "metadata", [item]))
        else:
            return annotation, metadata


def key_unit(key: str) -> str | None:
    """The unit of a numeric config key (``platoon.k_v`` -> ``1/s``, ``path.center[0]`` -> ``m``), for axis
    labels and messages; None for a key without one (a count, a factor, a word) or no such key."""
    parts = key.replace("[", ".").replace("]", "").split(".")
    loc = tuple(int(part) if part.isdigit() else part for part in parts if part)
    _, metadata = _field_at(loc)
    return next((str(item) for item in metadata if isinstance(item, (Unit, UnitNote))), None)


def _range_text(field: tuple[Any, list[Any]]) -> str:
    """"a finite number >= 0.001 and <= 1000", "an integer >= 1": the declared range of a numeric key."""
    annotation, metadata = field
    bounds = [f"{word} {_number(getattr(item, name))}" for item in metadata for name, word in _BOUND_WORDS
              if isinstance(item, getattr(annotated_types, name.capitalize())) and hasattr(item, name)]
    unit = next((f" {item}" for item in metadata if isinstance(item, Unit)), "")
    note = next((f" ({item})" for item in metadata if isinstance(item, UnitNote)), "")
    bounds = [bound + unit for bound in bounds]
    kind = "an integer" if annotation is int else "a finite number"
    text = " and ".join([f"{kind} {bounds[0]}" if bounds else kind, *bounds[1:]])
    return text + (" (radians: 90 degrees = 1.5708 rad)" if unit == " rad" else note)


def _number(value: float | int) -> str:
    return f"{value:g}" if isinstance(value, float) else str(value)


def _nearest_key(loc: tuple[Any, ...]) -> str:
    """" (did you mean count?)" for an unknown key ``loc``: the nearest key its table has, if any is near."""
    table, _ = _field_at(loc[:-1])
    if not (isinstance(table, type) and issubclass(table, BaseModel)) or not isinstance(loc[-1], str):
        return ""
    table_key = _key_of(loc[:-1])
    return did_you_mean(loc[-1], table.model_fields, f"{table_key}." if table_key else "")


def _explain(error: ValidationError) -> str:
    """One line for the first problem pydantic found: key, value, expectation."""
    first = error.errors(include_url=False)[0]
    ctx = first.get("ctx") or {}
    loc = tuple(part for part in first["loc"] if not (isinstance(part, str) and part.startswith("function-")))
    key = _key_of(loc)
    if "error" in ctx and isinstance(ctx["error"], (_RuleError, _Ros2Rule)):  # a rule of a nested table names its own key
        return f"{key}.{ctx['error']}" if key else str(ctx["error"])
    key = key or "a key"  # the key itself is what is wrong (not UTF-8)
    if first["type"] == "extra_forbidden":
        return f"{key}: unknown key{_nearest_key(loc)}"
    if first["type"] == "missing":
        return f"{key}: missing (required)"
    if "error" in ctx and isinstance(ctx["error"], _Expected):
        return f"{key} = {first['input']!r}: {ctx['error']}"
    if first["type"] in ("string_pattern_mismatch", "string_too_long") and loc == ("name",):
        return (f"name = {first['input']!r}: must be {NAME_RULE} (it names the trace file runs/<name>-<time>.mcap; "
                "without a name key it is the config's file name)")
    if first["type"] == "string_unicode":
        return f"{key} = {first['input']!r}: must be valid UTF-8 text"
    if first["type"] in _RANGE_ERRORS:
        return f"{key} = {first['input']!r}: must be {_range_text(_field_at(loc))}"
    message = first["msg"]
    message = message[0].lower() + message[1:] if message else message
    return f"{key} = {first['input']!r}: {message}"


def config_from_mapping(raw: dict[str, Any]) -> Config:
    try:
        return Config.model_validate(raw)
    except ValidationError as error:
        raise ConfigError(_explain(error)) from None


FILE_KEYS = ("zenoh_config",)  # keys of [vehicles.K] that name a file


def resolve_named_files(raw: dict[str, Any], folder: Path) -> None:
    """Make the files a config file names relative to that file's ``folder`` (not to the current folder:
    a config runs the same from anywhere). Values given with ``--set`` stay relative to the current
    folder, as every path typed on a command line."""
    hil = raw.get("hil")
    if isinstance(hil, dict) and isinstance(hil.get("lab_key"), str) and hil["lab_key"]:
        hil["lab_key"] = str(folder / Path(hil["lab_key"]).expanduser())  # an absolute one stays as it is
    vehicles = raw.get("vehicles")
    if not isinstance(vehicles, dict):
        return  # validation names the problem
    for table in vehicles.values():
        if not isinstance(table, dict):
            continue
        for key in FILE_KEYS:
            value = table.get(key)
            if isinstance(value, str) and value and not Path(value).is_absolute():
                table[key] = str(folder / value)


def parse_config(text: str, default_name: str, overrides: list[str] | tuple[str, ...] = (),
                 folder: Path | None = None) -> tuple[Config, dict[str, Any]]:
    """Parse, override and validate a config's text; returns the config and the raw mapping. ``folder``:
    the config file's folder, which the files it names are relative to (``resolve_named_files``)."""
    try:
        raw = tomllib.loads(text)
    except tomllib.TOMLDecodeError as error:
        raise ConfigError(f"not valid TOML: {error}") from None
    raw.setdefault("name", default_name)
    if folder is not None:
        resolve_named_files(raw, folder)
    for assignment in overrides:
        apply_override(raw, assignment)
    return config_from_mapping(raw), raw


def load_config(path: str | Path, overrides: list[str] | tuple[str, ...] = ()) -> tuple[Config, dict[str, Any]]:
    """Read, override and validate a scenario; returns the config and the raw mapping it came from."""
    return parse_config(read_config_text(path), Path(path).stem, overrides, Path(path).parent)
