"""The tables of a config, one model each ([simulation], [path], [m3pi], [platoon], [validity], [initial],
[vehicles.K], [remote], [hil], [[disturbance]]): keys, defaults, ranges and the rules within one table. The
root model and the rules across tables are in config.py, the [links] tables in link_config.py."""

from __future__ import annotations

from typing import Annotated, Literal

from pydantic import Field, model_validator

from bridge.protocol import DEFAULT_PREFIX, check_prefix
from fmus.model.dynamics import (M3PI_MOTOR_TIME_CONSTANT, M3PI_TRACK, M3PI_WHEEL_DEADBAND, M3PI_WHEEL_GAIN,
                                 M3PI_WHEEL_SPEED_MAX)
from fmus.model.robot_loop import LATENCY_MAX, M3PI_COMMAND_LATENCY, M3PI_POSE_LATENCY

from .config_logic import TARGET_VEHICLE, DisturbanceLogic, M3piLogic, PlatoonLogic
from .config_types import (LENGTH_MAX, SMALL, Angle, Duration, Gain, Length, PositiveLength, Pulse, Speed,
                           Text, Unit, rule, StrictModel)
from .raw_config import DEFAULT_COUNT, DEFAULT_STEP, DEFAULT_STOP_TIME, DEFAULT_TRACE_EVERY
from .ros2_config import VehicleRos2

class Simulation(StrictModel):
    stop_time: Duration = Field(DEFAULT_STOP_TIME, description="simulated time, s")
    step: Duration = Field(DEFAULT_STEP, description="communication step, s (at most stop_time)")
    master: Literal["jacobi", "gauss-seidel"] = "jacobi"
    coupling: Literal["extrapolate", "hold"] = "extrapolate"
    max_substep: Duration = Field(0.01, description="longest RK4 substep inside an FMU, s")
    trace_every: int = Field(DEFAULT_TRACE_EVERY, ge=1, description="record every K-th communication point (at most the step count)")
    fmus: Literal["native", "python"] | None = Field(
        None, description="FMUs to step: native (C, no Python on the host) or python (pythonfmu); "
                          "default native where a C compiler can build them (orchestrator/components/kinds.py)")


class PathConfig(StrictModel):
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


class M3pi(M3piLogic, StrictModel):
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

class M3piOverride(StrictModel):
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


class Platoon(PlatoonLogic, StrictModel):
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

class Validity(StrictModel):
    """Where a run stops being the model's (orchestrator/analysis/validity.py; docs/model.md, section 12): it
    keeps running, and says so in its summary, its log, `platoon report --json` and a sweep's row."""

    min_gap: GapLength | None = Field(None, description="m: a gap at or below it is a collision (default: a vehicle's "
                                      "size, 4.5 m or the m3pi's 0.095 m, at most half the equilibrium gap)")
    max_speed: Speed | None = Field(None, description="m/s: a faster vehicle has left the model (default: 3 V_c for "
                                    "kinematic vehicles; an m3pi is bounded by its wheels)")


class Initial(StrictModel):
    """Default placement: on the path behind the target, spaced by the chord d*, then perturbed."""

    radial_offset: Length = Field(0.0, description="vehicle 1 moved this far off the path (outward), m")
    heading_error: Angle = Field(0.0, description="added to vehicle 1's heading, rad")
    speed_factor: Annotated[float, Field(ge=SMALL, le=10.0)] = Field(1.0, description="every vehicle starts at this fraction of V_c")


class VehicleState(StrictModel):
    x: Length
    y: Length
    heading: Angle
    speed: Speed


class VehicleOverride(StrictModel):
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
                raise rule(key, value, problems[0])
        return self


class Remote(StrictModel):
    """Remote vehicles (docs/remote.md): how patient the run is with their servers."""

    step_timeout: Annotated[float, Unit("s")] = Field(2.0, gt=0.0, le=600.0, description="s to wait for a server's reply "
                                                                                       "to one call: then the run fails")
    connect_timeout: Annotated[float, Unit("s")] = Field(10.0, gt=0.0, le=600.0, description="s to wait for each server "
                                                                                          "at the start")


class Hil(StrictModel):
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
            raise rule("prefix", self.prefix, problems[0])
        return self




class Disturbance(DisturbanceLogic, StrictModel):
    # 1 .. platoon.count, or 0: the virtual target (a speed push only: the head's speed, prescribed)
    vehicle: int = Field(ge=TARGET_VEHICLE)
    kind: Literal["lateral_acceleration", "speed"]
    start: Annotated[float, Field(ge=0.0), Unit("s")]
    duration: Duration
    value: Pulse = Field(description="m/s² for kind lateral_acceleration, m/s for kind speed")
    # 0: a rectangular pulse of height value; > 0: value * sin(frequency (t - start)) over the same window,
    # a sinusoid to measure the speed chain's gain at one frequency (docs/model.md, section 12)
    frequency: Annotated[float, Field(ge=0.0, le=1e4), Unit("rad/s")] = 0.0
