"""The orchestrator's side of remote vehicles: which vehicles run in a ``platoon serve``, and their components.

A config marks vehicle K remote with ``[vehicles.K] endpoint = "remote"``; here that becomes a
``bridge.fmu_client.RemoteComponent`` with the parameters the local Vehicle FMU would have received
(the scenario's, as ``FmuComponent`` gets them) and the local FMU's inputs and outputs, which the server's
FMU must match. All of a run's remote vehicles share one Zenoh session, connected to every server.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from orchestrator.scenario.wiring import vehicle_name

if TYPE_CHECKING:
    from orchestrator.scenario.config import Config
    from fmus.component import Component
    from orchestrator.components.fmu import UnpackedFmu
    from orchestrator.scenario.scenario import Scenario


class RemoteRunError(ValueError):
    """A run option or config that cannot work with remote vehicles (the text says which and why)."""


def remote_names(config: Config) -> set[str]:
    return {vehicle_name(k) for k in config.remote_vehicles()}


def check_remote_options(config: Config, engine: str) -> None:
    """Remote vehicles run on the Python engine (the native core steps local FMUs only), and share one
    Zenoh session, so they name at most one Zenoh config file."""
    remote = config.remote_vehicles()
    if not remote:
        return
    names = ", ".join(vehicle_name(k) for k in remote)
    if engine != "python":
        raise RemoteRunError(f"--engine {engine}: {names} is remote (endpoint = \"remote\"); runs with remote "
                             "vehicles use the python engine (the default when a config has one)")
    files = {config.override(k).zenoh_config for k in remote} - {None}
    if len(files) > 1:
        raise RemoteRunError(f"vehicles {names}: remote vehicles share one Zenoh session, so at most one "
                             f"zenoh_config among them (got {', '.join(sorted(files))})")


def server_name(config: Config, vehicle: int) -> str:
    return config.override(vehicle).server or vehicle_name(vehicle)


def remote_components(config: Config, scenario: "Scenario", fmus: dict[str, "UnpackedFmu"]) -> dict[str, "Component"]:
    """The components of the run's remote vehicles, by component name ({} without remote vehicles)."""
    remote = config.remote_vehicles()
    if not remote:
        return {}
    from bridge.fmu_client import RemoteComponent, RemoteHost
    from bridge.fmu_wire import fmu_key

    overrides = {k: config.override(k) for k in remote}
    connect = tuple(dict.fromkeys(e for o in overrides.values() for e in o.connect or ()))
    listen = tuple(dict.fromkeys(e for o in overrides.values() for e in o.listen or ()))
    files = [o.zenoh_config for o in overrides.values() if o.zenoh_config]
    host = RemoteHost(connect, listen, files[0] if files else None, config.hil.allow_insecure)
    specs = {spec.name: spec for spec in scenario.components}
    components: dict[str, Component] = {}
    for vehicle, override in overrides.items():
        spec = specs[vehicle_name(vehicle)]
        fmu = fmus[spec.fmu]
        inputs = [v.name for v in fmu.description.modelVariables if v.causality == "input"]
        outputs = [v.name for v in fmu.description.modelVariables if v.causality == "output"]
        starts = fmu.start_values()
        where = ", ".join(override.connect or override.listen or ()) or (override.zenoh_config or "its Zenoh config")
        components[spec.name] = RemoteComponent(
            spec.name, fmu_key(override.prefix or config.hil.prefix, server_name(config, vehicle)), where,
            dict(spec.parameters), inputs, outputs, [float(starts[n]) for n in inputs], host,
            config.remote.step_timeout, config.remote.connect_timeout)
    return components
