"""From a validated config to what the master runs: components, parameters, wiring, disturbances.

Nothing here steps anything; it only decides who exists, with which FMU parameters, where each
vehicle starts, how they are connected and which inputs follow a schedule.
"""

from __future__ import annotations

import math

from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

from fmus.model.guidance import SENSING_LAWS
from fmus.model.paths import make_path

from orchestrator.scenario.raw_config import step_count  # noqa: F401  (re-exported: the engines import it from here)
from orchestrator.scenario.wiring import (LINK_FMU, TARGET, Connection, component_names, link_name, platoon_connections,
                                          vehicle_name)

if TYPE_CHECKING:
    from orchestrator.scenario.config import Config

DISTURBANCE_INPUTS = {
    "lateral_acceleration": "disturbance.lateral_acceleration",
    "speed": "disturbance.speed",
}

# A communication point t is inside [start, start + duration) up to this much rounding.
TIME_TOLERANCE = 1e-9


@dataclass(frozen=True)
class ScheduledInput:
    """A rectangular pulse on one input: ``value`` on [start, start + duration), zero elsewhere; with a
    ``frequency`` w > 0 (rad/s), ``value * sin(w (t - start))`` on that window instead.

    Sampled at communication points and held over the step, in the co-simulation and in the
    monolithic reference alike (the native core computes the same ``sin``, C's, which Python's calls).
    """

    component: str
    input: str
    start: float
    duration: float
    value: float
    frequency: float = 0.0

    def value_at(self, t: float) -> float:
        if self.start - TIME_TOLERANCE <= t < self.start + self.duration - TIME_TOLERANCE:
            if self.frequency > 0.0:
                return self.value * math.sin(self.frequency * (t - self.start))
            return self.value
        return 0.0


@dataclass(frozen=True)
class ComponentSpec:
    name: str
    fmu: str  # "VirtualTarget" | "Vehicle" | "Link"
    parameters: dict[str, Any]


@dataclass(frozen=True)
class Scenario:
    config: Config
    components: list[ComponentSpec]
    connections: list[Connection]
    schedules: list[ScheduledInput] = field(default_factory=list)

    @property
    def vehicle_count(self) -> int:
        return self.config.platoon.count

    def path(self):
        return path_of(self.config)


def path_of(config: Config):
    p = config.path
    direction = 1 if p.direction == "ccw" else -1
    return make_path(p.kind, p.radius, p.center[0], p.center[1], p.heading, direction)


def initial_states(config: Config) -> list[tuple[float, float, float, float]]:
    """(x, y, heading, speed) of each vehicle: on the path, one chord d* apart, then perturbed."""
    path = path_of(config)
    spacing = path.arc_for_chord(config.platoon.d_star)
    speed = config.initial.speed_factor * config.platoon.speed
    states = []
    for index in range(1, config.platoon.count + 1):
        x, y, heading = path.pose_at(-index * spacing)
        if index == 1:
            nx, ny = path.outward_normal(x, y)
            x += config.initial.radial_offset * nx
            y += config.initial.radial_offset * ny
            heading += config.initial.heading_error
        explicit = config.override(index).initial
        if explicit is not None:
            x, y, heading, speed_i = explicit.x, explicit.y, explicit.heading, explicit.speed
        else:
            speed_i = speed
        states.append((x, y, heading, speed_i))
    return states


def speed_law_parameters(config: Config, index: int) -> dict[str, Any]:
    """Vehicle ``index``'s speed law, with its time gap, standstill gap and gain under acc and cacc only:
    the paper's law reads none of them, and keeps the FMU's defaults (a d* below h V_c, whose default
    standstill gap d* - h V_c would be negative, then means nothing)."""
    law = config.speed_law_of(index)
    if law not in SENSING_LAWS:
        return {"speed_law": law}
    p = config.platoon
    return {"speed_law": law, "time_gap": p.time_gap, "standstill_gap": p.resolved_standstill_gap,
            "cacc_gain": p.cacc_gain}


def speed_limit_parameters(config: Config, index: int) -> dict[str, Any]:
    """A kinematic vehicle's speed limit where the config sets one (none otherwise: the FMU's default 0 is no
    limit, so a run without it has the parameters, and the trace, it had before the limit existed)."""
    limit = config.platoon.speed_max
    return {} if limit is None or config.dynamics_of(index) != "kinematic" else {"speed_max": limit}


def build_scenario(config: Config) -> Scenario:
    sim, platoon, path = config.simulation, config.platoon, config.path
    common = {"d_star": platoon.d_star, "coupling": sim.coupling, "max_substep": sim.max_substep}
    target = ComponentSpec(
        TARGET,
        "VirtualTarget",
        {
            "path.kind": path.kind,
            "path.radius": path.radius,
            "path.x0": path.center[0],
            "path.y0": path.center[1],
            "path.heading": path.heading,
            "path.direction": 1 if path.direction == "ccw" else -1,
            "initial.arc_length": 0.0,
            "speed_law": config.speed_law_of(1),  # the lead's: acc and cacc need no forward information
            "v_c": platoon.speed,
            **common,
        },
    )
    components = [target]
    for index, (x, y, heading, speed) in enumerate(initial_states(config), start=1):
        override = config.override(index)
        components.append(
            ComponentSpec(
                vehicle_name(index),
                "Vehicle",
                {
                    "law": override.law or platoon.law,
                    "k_v": override.k_v or platoon.k_v,
                    "v_c": platoon.speed,
                    "is_last": index == platoon.count,
                    "dynamics": config.dynamics_of(index),
                    "initial.x": x,
                    "initial.y": y,
                    "initial.heading": heading,
                    "initial.speed": speed,
                    **config.m3pi_of(index).parameters(),
                    **speed_law_parameters(config, index),
                    **speed_limit_parameters(config, index),
                    **common,
                },
            )
        )
    schedules = [
        ScheduledInput(TARGET if d.on_target else vehicle_name(d.vehicle), DISTURBANCE_INPUTS[d.kind], d.start,
                       d.duration, d.value, d.frequency)
        for d in config.disturbance
    ]
    links = link_specs(config)
    sensing = config.sensing_vehicles()
    if not links:  # every link perfect: today's wiring, component for component
        return Scenario(config, components, platoon_connections(platoon.count, sensing=sensing), schedules)
    linked = frozenset(links)
    order = component_names(platoon.count, linked)
    by_name = {spec.name: spec for spec in components} | {spec.name: spec for spec in links.values()}
    return Scenario(config, [by_name[name] for name in order], platoon_connections(platoon.count, linked, sensing),
                    schedules)


def monolithic_refusal(config: Config, set_links: tuple[str, ...] = ()) -> str | None:
    """Why the monolithic reference cannot run ``config`` (it has links, or robots with latencies), or None;
    ``set_links``: the keys of the ``--set`` options that made the links, named instead of a [links] table the
    config may not have."""
    linked = config.linked()
    if linked:
        without = f"without --set {', '.join(set_links)}" if set_links else "without the [links] table"
        return (f"the monolithic reference has no messages, so it cannot run links ({len(linked)} in this config, "
                f"docs/links.md); run without --monolithic, or {without}")
    sampled = [i for i in config.m3pi_vehicles() if config.m3pi_of(i).samples]
    if sampled:
        return (f"the monolithic reference is one continuous system, so it cannot run a robot's sampled loop with "
                f"latencies (m3pi.command_latency, m3pi.pose_latency > 0 on vehicle {sampled[0]}; docs/model.md, \"A "
                "robot that is not its nominal model\"); run without --monolithic, or with latencies of 0")
    return None


def link_specs(config: Config) -> dict[tuple[str, int], ComponentSpec]:
    """The Link components of the run by (direction, vehicle): one per link that is not perfect (a
    perfect link is a plain connection, exactly as without a [links] table)."""
    specs = {}
    for direction, vehicle in config.linked():
        link = config.resolve_link(direction, vehicle)
        parameters = {"delay": link.delay, "jitter": link.jitter, "period": link.period, "loss": link.loss,
                      "burst": link.burst, "seed": link.seed, "stream": link.stream}
        specs[(direction, vehicle)] = ComponentSpec(link_name(direction, vehicle), LINK_FMU, parameters)
    return specs

