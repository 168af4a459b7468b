"""What a validated config answers (a vehicle's laws, its robot, its links, the step count): the methods of the
config's models, without pydantic.

The models (config.py, config_tables.py) declare the schema and validate with pydantic; these mixins hold
what they compute once valid, so that the same methods serve a config read back from the cache of validated
configs (config_records.py), which a `platoon run` or `platoon report` of a config seen before uses without
loading pydantic (docs/performance.md, "Start-up"). No pydantic here, nor in anything imported here.
"""

from __future__ import annotations

from dataclasses import fields
from pathlib import Path
from typing import Any

from fmus.model.guidance import SENSING_LAWS
from fmus.model.link import LinkParameters

from .raw_config import FILE_KEYS, step_count

LINK_DIRECTIONS = ("backward", "forward")
# The keys a [links] table may set: a link's parameters but its stream (link_config.py's ``LinkKeys`` declares
# them; tests/test_config_cache.py holds the two equal)
LINK_KEYS = tuple(field.name for field in fields(LinkParameters) if field.name != "stream")


def link_stream(direction: str, vehicle: int) -> int:
    """A link's own stream of the seed: 2 (N - 1) for vehicle N's backward link, + 1 for its forward one."""
    return 2 * (vehicle - 1) + LINK_DIRECTIONS.index(direction)


def resolve_link(links: Any, direction: str, vehicle: int) -> LinkParameters:
    """The settings of vehicle ``vehicle``'s ``direction`` link (``links``: the config's [links]): each key from
    the narrowest table that sets it ([links.vehicles.N.direction], [links.direction], [links]), else the
    perfect link's."""
    own = links.vehicles.get(str(vehicle))
    layers = ([getattr(own, direction)] if own is not None else []) + [getattr(links, direction), links]
    default = LinkParameters()
    values = {key: next((getattr(t, key) for t in layers if getattr(t, key) is not None), getattr(default, key))
              for key in LINK_KEYS}
    return LinkParameters(**values, stream=link_stream(direction, vehicle))


class ConfigLogic:
    """The root config's answers (``Config``); ``_no_override`` and ``_no_links`` are the default [vehicles.K]
    and [links] tables of the class at hand (a pydantic model's, or a cached record's)."""

    def speed_law_of(self, vehicle: int) -> str:
        """Vehicle ``vehicle``'s speed law: its [vehicles.K] override, else platoon.speed_law."""
        return self.override(vehicle).speed_law or self.platoon.speed_law

    def sensing_vehicles(self) -> list[int]:
        """Numbers of the vehicles whose speed law reads the on-board sensor (acc, cacc), front to back."""
        return [i for i in range(1, self.platoon.count + 1) if self.speed_law_of(i) in SENSING_LAWS]

    def linked(self) -> list[tuple[str, int]]:
        """The (direction, vehicle) pairs whose link is not perfect: the run's Link components."""
        if self.links == self._no_links():
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

    def override(self, vehicle: int) -> Any:
        """Vehicle ``vehicle``'s [vehicles.K] table: every key at its default when the config has none."""
        table = self.vehicles.get(str(vehicle))
        return self._no_override() if table is None else table

    def dynamics_of(self, vehicle: int) -> str:
        """Vehicle ``vehicle``'s dynamics: its [vehicles.K] override, else platoon.dynamics."""
        return self.override(vehicle).dynamics or self.platoon.dynamics

    def m3pi_of(self, vehicle: int) -> Any:
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


class M3piLogic:
    """[m3pi]'s answers (``M3pi``)."""

    @property
    def samples(self) -> bool:
        """A robot with latencies: the live run's sampled loop (fmus.model.robot_loop), not the continuous model."""
        return self.command_latency > 0.0 or self.pose_latency > 0.0

    def parameters(self) -> dict[str, float]:
        """The Vehicle FMU's ``m3pi.*`` parameters of these constants."""
        return {f"m3pi.{key}": value for key, value in self.model_dump().items()}


class PlatoonLogic:
    """[platoon]'s answers (``Platoon``)."""

    @property
    def resolved_standstill_gap(self) -> float:
        """r: as given, or the one that makes the acc/cacc equilibrium gap d* at V_c (d* - h V_c)."""
        if self.standstill_gap is not None:
            return self.standstill_gap
        return self.d_star - self.time_gap * self.speed


TARGET_VEHICLE = 0  # a disturbance's ``vehicle`` naming the virtual target, the platoon's head
PULSE_UNITS = {"lateral_acceleration": "m/s²", "speed": "m/s"}  # a disturbance's value, by its kind


class DisturbanceLogic:
    """A [[disturbance]]'s answers (``Disturbance``)."""

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


# The mixin of each model that has one, by the model's class name (config_records.py builds a cached config's
# records on them)
LOGIC: dict[str, type] = {"Config": ConfigLogic, "M3pi": M3piLogic, "Platoon": PlatoonLogic,
                          "Disturbance": DisturbanceLogic}
