"""Scenario configuration: TOML files, ``--set KEY=VALUE`` overrides, validation with clear errors.

Every key is documented in docs/config.md. Validation is pydantic in strict mode (a count must be an
integer, a law one of the known names), plus the cross-field rules a platoon needs (d* fits the
circle, disturbances name existing vehicles). A bad config raises ``ConfigError`` whose message is one
line naming the key, the value and what was expected.

Every number has a declared range, in one place: the annotated types of config_types.py (``Positive``,
``Angle``, ...), which pydantic enforces and config_errors.py quotes back (``platoon.k_v = inf: must be a
finite number >= 0.001 and <= 1000``). No float key accepts inf or NaN (``allow_inf_nan=False`` for all).

Here: the root model with the rules across tables, and reading a config (``parse_config``, ``load_config``).
The tables are in config_tables.py and link_config.py, the words a run's header says of a config in
config_text.py.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

from pydantic import Field, ValidationError, model_validator

from fmus.model.integrate import substep_count
from fmus.model.link import CAPACITY as LINK_CAPACITY
from fmus.model.link import messages_held
from fmus.model.link import parameter_errors as link_parameter_errors
from fmus.model.robot_loop import COMMAND_CAPACITY

from .config_errors import explain, unit_of
from .config_logic import ConfigLogic
from .config_tables import TARGET_VEHICLE  # noqa: F401  (re-exported: the analyses name the target by it)
from .config_tables import (Disturbance, Hil, Initial, M3pi, PathConfig, Platoon, Remote, Simulation, Validity,
                            VehicleOverride)
from .config_types import COUNT_LIMIT, RK4_STABILITY, Name, Text, rule, RuleError, StrictModel
from .link_config import LINK_DIRECTIONS, Links
from .raw_config import ConfigError, apply_override, read_config_text, step_count  # noqa: F401  (re-exported)
from .raw_config import parse_value  # noqa: F401  (re-exported: a --set value's parser, where it always was)
from .raw_config import FILE_KEYS, raw_mapping, resolve_named_files  # noqa: F401  (re-exported)
from .ros2_config import RunRos2


class Config(ConfigLogic, StrictModel):
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
            raise rule("platoon.d_star", self.platoon.d_star, f"less than 2 * path.radius = {2.0 * self.path.radius} "
                        "(a chord of the circle shorter than its diameter: at d* = 2R the equilibrium is degenerate)")
        for index, item in enumerate(self.disturbance):
            if item.vehicle > count:
                raise rule(f"disturbance[{index}].vehicle", item.vehicle, f"a vehicle number from 1 to platoon.count = {count} "
                            "(or 0, the virtual target)")
            if item.on_target and item.kind != "speed":
                raise rule(f"disturbance[{index}].kind", item.kind, '"speed" on vehicle 0 (the virtual target has no '
                            'guidance to push sideways: push vehicle 1 instead)')
        for key, vehicle in self.vehicles.items():
            if not key.isdigit() or key != str(int(key)) or not 1 <= int(key) <= count:
                raise rule(f"vehicles.{key}", key, f"a vehicle number from 1 to platoon.count = {count}")
            if vehicle.endpoint == "zenoh" and (vehicle.dynamics or self.platoon.dynamics) != "m3pi":
                raise rule(f"vehicles.{key}.endpoint", "zenoh", 'm3pi dynamics, since a live robot is an m3pi: set '
                            f'platoon.dynamics = "m3pi" (or vehicles.{key}.dynamics)')
        robots = [(v.prefix or self.hil.prefix, self.robot_id(int(k))) for k, v in self.vehicles.items()
                  if v.endpoint == "zenoh"]
        if len(set(robots)) != len(robots):
            raise rule("vehicles", [f"{p}/m3pi/{r}" for p, r in robots], "one live vehicle per robot (prefix and id)")
        sim = self.simulation
        if sim.step > sim.stop_time:
            raise rule("simulation.step", sim.step, f"at most simulation.stop_time = {sim.stop_time}")
        steps, substeps = sim.stop_time / sim.step, max(1.0, sim.step / sim.max_substep)  # floats: may be inf
        if steps * substeps > COUNT_LIMIT:  # no option lifts this one (orchestrator/scenario/limits.py: the adjustable ones)
            raise RuleError("simulation", None, "", message=(
                f"simulation: {steps:.3g} steps (stop_time / step) x {substeps:.3g} RK4 substeps each (step / "
                f"max_substep) = {steps * substeps:.3g} substeps per FMU: expected at most 2**53 = {COUNT_LIMIT:.3g} "
                "(beyond it step counts are not exact in double precision; no option lifts this)"))
        self._check_speed_laws()
        if self.platoon.speed_max is not None and self.platoon.speed_max < self.platoon.speed:
            raise rule("platoon.speed_max", self.platoon.speed_max, f"at least platoon.speed = {self.platoon.speed:g} "
                        "m/s (a limit below the cruise speed keeps the platoon from ever reaching it)")
        self._check_robots()
        self._check_stiffness()
        self._check_links()
        if sim.trace_every > self.steps:
            raise rule("simulation.trace_every", sim.trace_every, f"at most the run's {self.steps} steps "
                        "(stop_time / step), so that a point after t = 0 is recorded")
        return self

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
                raise rule(key, self.speed_law_of(index), f"acc or cacc behind vehicle {index - 1}, whose "
                            f"{self.speed_law_of(index - 1)} law does not read its follower's gap: a paper vehicle's "
                            "gap is regulated by the vehicle ahead, so behind an acc or cacc one it would drift")
        if p.standstill_gap is None and sensing and p.resolved_standstill_gap < 0.0:
            raise rule("platoon.time_gap", p.time_gap, f"at most platoon.d_star / platoon.speed = {p.d_star / p.speed:g} s "
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
                raise rule(self.m3pi_key(vehicle, "wheel_deadband"), m3pi.wheel_deadband,
                            f"below vehicle {vehicle}'s wheel_speed_max = {m3pi.wheel_speed_max:g} m/s (a dead-band at "
                            "or above the limit keeps the wheels still whatever the run commands)")
            delay, step = m3pi.command_latency + m3pi.pose_latency, self.simulation.step
            if math.ceil(delay / step) + 1 > COMMAND_CAPACITY:
                raise RuleError("m3pi", None, "", message=(
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
            raise rule("simulation.max_substep", sim.max_substep,
                        f"RK4 substeps of at most {RK4_STABILITY:g} x the fastest lag, here {key} (time constant "
                        f"{lag:g} s): max_substep <= {RK4_STABILITY * lag:.3g} s (the substep is now {h:.3g} s; "
                        "beyond it the integration diverges)")

    def _check_links(self) -> None:
        """Links name existing vehicles, their losses can be bursty as asked, and none holds more
        messages than a Link FMU can (fmus.model.link.CAPACITY)."""
        count = self.platoon.count
        for key in self.links.vehicles:
            if not key.isdigit() or key != str(int(key)) or not 1 <= int(key) <= count:
                raise rule(f"links.vehicles.{key}", key, f"a vehicle number from 1 to platoon.count = {count}")
        if self.links == self._no_links():
            return  # no link: nothing to check for any of the vehicles
        for vehicle in range(1, count + 1):
            for direction in LINK_DIRECTIONS:
                link = self.resolve_link(direction, vehicle)
                where = f"links (vehicle {vehicle}'s {direction} link)"
                errors = link_parameter_errors(link)
                if errors:
                    raise RuleError("links", None, "", message=f"{where}: {errors[0]}")
                held = messages_held(link, self.simulation.step)
                if held > LINK_CAPACITY:
                    raise RuleError("links", None, "", message=(
                        f"{where}: delay + jitter = {link.delay + link.jitter:g} s spans up to {held} messages at "
                        f"step {self.simulation.step:g} s and period {link.period:g} s; a link holds at most "
                        f"{LINK_CAPACITY} (shorten the delay, or send beacons less often: links.period)"))

    def _no_override(self) -> VehicleOverride:
        return NO_OVERRIDE

    def _no_links(self) -> Links:
        return NO_LINKS


def config_from_mapping(raw: dict[str, Any]) -> Config:
    try:
        return Config.model_validate(raw)
    except ValidationError as error:
        raise ConfigError(explain(error, Config)) from None


def key_unit(key: str) -> str | None:
    """The unit of a numeric config key (``platoon.k_v`` -> ``1/s``, ``path.center[0]`` -> ``m``), for axis
    labels and messages; None for a key without one (a count, a factor, a word) or no such key."""
    return unit_of(Config, key)


# A vehicle without a [vehicles.K] table: every key at its default. Constructed, not validated (a default is never
# validated, so it is the same model), which spares every run building the table's own validator (~1 % of a run).
NO_OVERRIDE = VehicleOverride.model_construct()
NO_LINKS = Links.model_construct()  # every link perfect: what a config without [links] has


def parse_config(text: str, default_name: str, overrides: list[str] | tuple[str, ...] = (),
                 folder: Path | None = None) -> tuple[Config, dict[str, Any]]:
    """Parse, override and validate a config's text; returns the config and the raw mapping. ``folder``:
    the config file's folder, which the files it names are relative to (``resolve_named_files``)."""
    raw = raw_mapping(text, default_name, overrides, folder)
    return config_from_mapping(raw), raw


def load_config(path: str | Path, overrides: list[str] | tuple[str, ...] = ()) -> tuple[Config, dict[str, Any]]:
    """Read, override and validate a scenario; returns the config and the raw mapping it came from."""
    return parse_config(read_config_text(path), Path(path).stem, overrides, Path(path).parent)
