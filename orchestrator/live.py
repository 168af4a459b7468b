"""The orchestrator's side of hardware in the loop: which vehicles are live, and what their links report.

A config marks vehicle K live with ``[vehicles.K] endpoint = "zenoh"``; here that becomes a
``bridge.live.LiveVehicle`` with the very parameter values the Vehicle FMU would have received (its
declared defaults, then the scenario's), its inputs and outputs named as the FMU's. During the run,
``LiveReporter`` moves what the live components saw (state changes, dropped messages, raw poses and
commands, link statistics) into the trace, and sums it up at the end. The bridge knows Zenoh, not
the trace; this module knows the trace's writer, not Zenoh.
"""

from __future__ import annotations

import json
from typing import Any, Sequence

from .components import UnpackedFmu
from .config import Config
from .interface import Component, LiveComponent
from .realtime import Pacer
from .scenario import ComponentSpec
from .wiring import vehicle_name

LINK_STATS_INTERVAL = 1.0  # s of simulated (= wall) time between two link statistics messages


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

    override, hil = config.override(vehicle), config.hil
    return LiveSettings(
        robot=config.robot_id(vehicle),
        prefix=override.prefix or hil.prefix,
        connect=tuple(override.connect or ()),
        listen=tuple(override.listen or ()),
        zenoh_config=override.zenoh_config,
        pose_timeout=hil.pose_timeout,
        connect_timeout=hil.connect_timeout,
        command_validity=hil.command_validity,
        max_pose_age=hil.max_pose_age,
        allow_insecure=hil.allow_insecure,
    )


def live_component(spec: ComponentSpec, fmu: UnpackedFmu, config: Config, vehicle: int) -> Component:
    """The live robot standing in for ``spec``'s Vehicle FMU."""
    from bridge.live import LiveVehicle

    settings = live_settings(config, vehicle)
    inputs = [v.name for v in fmu.description.modelVariables if v.causality == "input"]
    outputs = [v.name for v in fmu.description.modelVariables if v.causality == "output"]
    starts = fmu.start_values()
    return LiveVehicle(spec.name, {**starts, **spec.parameters}, inputs, outputs, [float(starts[n]) for n in inputs],
                       settings)


class LiveReporter:
    """Copies the live components' events and raw messages into the trace after each recorded point."""

    def __init__(self, components: Sequence[Component], writer: Any, pacer: Pacer) -> None:
        self.live = [c for c in components if isinstance(c, LiveComponent)]
        self.writer, self.pacer = writer, pacer
        self._next_stats = 0.0

    def __call__(self, t: float, final: bool = False) -> None:
        writer = self.writer
        for component in self.live:
            for event in component.drain_events():
                writer.log(t, event.level, event.message)
            for record in component.drain_records():
                writer.live(f"{component.name}/{record.stream}", t, record.fields)
        if t >= self._next_stats or final:
            self._next_stats = t + LINK_STATS_INTERVAL
            for component in self.live:
                numbers = {k: float(v) for k, v in component.link_statistics().items() if isinstance(v, (int, float))}
                writer.live(f"{component.name}/link", t, numbers)

    def finish(self, t: float) -> dict[str, dict[str, Any]]:
        """Drain what is left, record the links' final statistics (the last ``/link`` message always
        holds the final counts, however close to the previous one the run ended) and the summary as
        ``platoon.hil`` metadata, and return it."""
        self(t, final=True)
        summary = {"pacing": self.pacer.summary()}
        summary.update({c.name: c.link_statistics() for c in self.live})
        self.writer.metadata("platoon.hil", {name: json.dumps(values) for name, values in summary.items()})
        return summary
