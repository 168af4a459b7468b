"""Scenario configuration: TOML files, ``--set KEY=VALUE`` overrides, validation with clear errors.

Every key is documented in docs/config.md. Validation is pydantic in strict mode (a count must be an
integer, a law one of the known names), plus the cross-field rules a platoon needs (d* fits the
circle, disturbances name existing vehicles). A bad config raises ``ConfigError`` whose message is one
line naming the key, the value and what was expected.
"""

from __future__ import annotations

import tomllib
from pathlib import Path
from typing import Any, Literal

from pydantic import BaseModel, ConfigDict, Field, ValidationError, model_validator

from bridge.protocol import DEFAULT_PREFIX, check_prefix
from fmus.model.dynamics import M3PI_MOTOR_TIME_CONSTANT, M3PI_TRACK, M3PI_WHEEL_SPEED_MAX


class ConfigError(ValueError):
    """A configuration problem, phrased for the person who wrote the config."""


class _Strict(BaseModel):
    model_config = ConfigDict(extra="forbid", strict=True, frozen=True)



class Simulation(_Strict):
    stop_time: float = Field(100.0, gt=0.0, description="simulated time, s")
    step: float = Field(0.01, gt=0.0, description="communication step, s")
    master: Literal["jacobi", "gauss-seidel"] = "jacobi"
    coupling: Literal["extrapolate", "hold"] = "extrapolate"
    max_substep: float = Field(0.01, gt=0.0, description="longest RK4 substep inside an FMU, s")
    trace_every: int = Field(1, ge=1, description="record every K-th communication point")


class PathConfig(_Strict):
    kind: Literal["circle", "line"] = "circle"
    radius: float = Field(50.0, gt=0.0)
    center: list[float] = Field(default_factory=lambda: [0.0, 0.0], min_length=2, max_length=2)
    heading: float = 0.0
    direction: Literal["ccw", "cw"] = "ccw"


class M3pi(_Strict):
    track: float = Field(M3PI_TRACK, gt=0.0)
    wheel_speed_max: float = Field(M3PI_WHEEL_SPEED_MAX, gt=0.0)
    motor_time_constant: float = Field(M3PI_MOTOR_TIME_CONSTANT, gt=0.0)


Law = Literal["sine", "regular"]
DynamicsKind = Literal["kinematic", "m3pi"]


class Platoon(_Strict):
    count: int = Field(4, ge=1, le=10000)
    law: Law = "sine"
    d_star: float = Field(75.0, gt=0.0)
    k_v: float = Field(0.5, gt=0.0)
    speed: float = Field(25.0, gt=0.0, description="V_c, the last vehicle's commanded speed")
    dynamics: DynamicsKind = "kinematic"


class Initial(_Strict):
    """Default placement: on the path behind the target, spaced by the chord d*, then perturbed."""

    radial_offset: float = Field(0.0, description="vehicle 1 moved this far off the path (outward), m")
    heading_error: float = Field(0.0, description="added to vehicle 1's heading, rad")
    speed_factor: float = Field(1.0, gt=0.0, description="every vehicle starts at this fraction of V_c")


class VehicleState(_Strict):
    x: float
    y: float
    heading: float
    speed: float = Field(gt=0.0)


class VehicleOverride(_Strict):
    law: Law | None = None
    k_v: float | None = Field(None, gt=0.0)
    dynamics: DynamicsKind | None = None
    initial: VehicleState | None = None
    # Hardware in the loop (docs/hil.md): "zenoh" makes this vehicle a live m3pi robot on Zenoh; the keys
    # after it say where the robot is, and are ignored with "fmu".
    endpoint: Literal["fmu", "zenoh"] = "fmu"
    robot: int | None = Field(None, ge=0, le=2**31 - 1, description="robot id on Zenoh (default: the vehicle number)")
    prefix: str | None = Field(None, description="key prefix (default hil.prefix)")
    connect: list[str] | None = Field(None, description="Zenoh endpoints to connect to, e.g. tcp/127.0.0.1:7447")
    listen: list[str] | None = Field(None, description="Zenoh endpoints to listen on")
    zenoh_config: str | None = Field(None, description="Zenoh config file (JSON5): TLS, access control, ...")

    @model_validator(mode="after")
    def _prefix_is_a_key(self) -> "VehicleOverride":
        # robot, prefix, connect, listen and zenoh_config only act with endpoint = "zenoh"; they may stay
        # when a run sets endpoint = "fmu" (the same platoon all simulated, for comparison)
        if self.prefix is not None:
            problems = check_prefix(self.prefix)
            if problems:
                raise _rule("prefix", self.prefix, problems[0])
        return self


class Hil(_Strict):
    """Hardware in the loop: shared by every live vehicle of the run (docs/hil.md)."""

    prefix: str = Field(DEFAULT_PREFIX, description="Zenoh key prefix: <prefix>/m3pi/<id>/...")
    pose_timeout: float = Field(0.5, gt=0.0, le=5.0, description="s without a valid pose: the robot is lost")
    connect_timeout: float = Field(10.0, gt=0.0, le=600.0, description="s to wait for each robot at the start")
    command_validity: float = Field(0.1, gt=0.0, le=5.0, description="s: a command's deadline after it is sent")
    max_pose_age: float = Field(0.25, gt=0.0, le=5.0, description="s: an older pose is dropped as late")

    @model_validator(mode="after")
    def _prefix_is_a_key(self) -> "Hil":
        problems = check_prefix(self.prefix)
        if problems:
            raise _rule("prefix", self.prefix, problems[0])
        return self


class Disturbance(_Strict):
    vehicle: int = Field(ge=1)
    kind: Literal["lateral_acceleration", "speed"]
    start: float = Field(ge=0.0)
    duration: float = Field(gt=0.0)
    value: float


class Config(_Strict):
    name: str = "scenario"
    description: str = ""
    simulation: Simulation = Simulation()
    path: PathConfig = PathConfig()
    platoon: Platoon = Platoon()
    initial: Initial = Initial()
    m3pi: M3pi = M3pi()
    disturbance: list[Disturbance] = Field(default_factory=list)
    vehicles: dict[str, VehicleOverride] = Field(default_factory=dict)
    hil: Hil = Hil()

    @model_validator(mode="after")
    def _platoon_rules(self) -> "Config":
        count = self.platoon.count
        if self.path.kind == "circle" and self.platoon.d_star > 2.0 * self.path.radius:
            raise _rule("platoon.d_star", self.platoon.d_star, f"at most 2 * path.radius = {2.0 * self.path.radius} (a chord of the circle)")
        for index, item in enumerate(self.disturbance):
            if item.vehicle > count:
                raise _rule(f"disturbance[{index}].vehicle", item.vehicle, f"a vehicle number from 1 to platoon.count = {count}")
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
        if self.simulation.step > self.simulation.stop_time:
            raise _rule("simulation.step", self.simulation.step, f"at most simulation.stop_time = {self.simulation.stop_time}")
        return self

    def override(self, vehicle: int) -> VehicleOverride:
        return self.vehicles.get(str(vehicle), VehicleOverride())

    def live_vehicles(self) -> list[int]:
        """Numbers of the vehicles that are live robots, front to back."""
        return sorted(int(k) for k, v in self.vehicles.items() if v.endpoint == "zenoh")

    def robot_id(self, vehicle: int) -> int:
        robot = self.override(vehicle).robot
        return vehicle if robot is None else robot


class _RuleError(ValueError):
    def __init__(self, key: str, value: Any, expected: str) -> None:
        super().__init__(f"{key} = {value!r}: expected {expected}")
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


def _explain(error: ValidationError) -> str:
    """One line for the first problem pydantic found: key, value, expectation."""
    first = error.errors(include_url=False)[0]
    ctx = first.get("ctx") or {}
    loc = tuple(part for part in first["loc"] if not (isinstance(part, str) and part.startswith("function-")))
    key = _key_of(loc)
    if "error" in ctx and isinstance(ctx["error"], _RuleError):  # a rule of a nested table names its own key
        return f"{key}.{ctx['error']}" if key else str(ctx["error"])
    if first["type"] == "extra_forbidden":
        return f"{key}: unknown key"
    if first["type"] == "missing":
        return f"{key}: missing (required)"
    message = first["msg"]
    message = message[0].lower() + message[1:] if message else message
    return f"{key} = {first['input']!r}: {message}"


def parse_value(text: str) -> Any:
    """A ``--set`` value: any TOML value (7, 0.5, true, "x", [1, 2]); a bare word is a string."""
    try:
        return tomllib.loads(f"value = {text}")["value"]
    except tomllib.TOMLDecodeError:
        return text


def apply_override(raw: dict[str, Any], assignment: str) -> None:
    """Apply ``KEY=VALUE`` (dotted key) to the raw config mapping."""
    if "=" not in assignment:
        raise ConfigError(f"--set {assignment!r}: expected KEY=VALUE, e.g. platoon.count=7")
    key, text = assignment.split("=", 1)
    parts = key.strip().split(".")
    if not all(parts):
        raise ConfigError(f"--set {assignment!r}: {key!r} is not a dotted key like platoon.count")
    node = raw
    for index, part in enumerate(parts[:-1]):
        child = node.setdefault(part, {})
        if not isinstance(child, dict):
            raise ConfigError(f"--set {assignment!r}: {'.'.join(parts[: index + 1])} is not a table")
        node = child
    node[parts[-1]] = parse_value(text.strip())


def config_from_mapping(raw: dict[str, Any]) -> Config:
    try:
        return Config.model_validate(raw)
    except ValidationError as error:
        raise ConfigError(_explain(error)) from None


def load_config(path: str | Path, overrides: list[str] | tuple[str, ...] = ()) -> tuple[Config, dict[str, Any]]:
    """Read, override and validate a scenario; returns the config and the raw mapping it came from."""
    path = Path(path)
    try:
        text = path.read_text()
    except OSError as error:
        raise ConfigError(f"cannot read the file: {error.strerror}") from None
    try:
        raw = tomllib.loads(text)
    except tomllib.TOMLDecodeError as error:
        raise ConfigError(f"not valid TOML: {error}") from None
    raw.setdefault("name", path.stem)
    for assignment in overrides:
        apply_override(raw, assignment)
    return config_from_mapping(raw), raw
