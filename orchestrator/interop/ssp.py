"""SSP 1.0 export: the whole platoon of a config as one package that other tools run.

An SSP (System Structure and Parameterization, Modelica Association) package is a zip with
``SystemStructure.ssd`` at its root. Ours holds:

* ``resources/<Kind>.fmu``: the FMUs the platoon uses (VirtualTarget, Vehicle, LiveVehicle for a
  vehicle that is a live robot, RemoteVehicle for a vehicle served by a ``platoon serve``: docs/remote.md);
* ``resources/<component>.ssv``: each component's parameter values, exactly the ones our orchestrator
  sets (``build_scenario``), bound to it by a ParameterBinding;
* in the .ssd: every component with every input and output as a connector (units from the FMUs), the
  Fig. 2 connections of ``orchestrator.scenario.wiring`` (the list our master steps), the default experiment,
  and the Open Simulation Platform annotation that makes libcosim use its fixed-step algorithm with
  the config's step, on the calling thread by default (``numWorkerThreads="0"``: pythonfmu FMUs
  share one interpreter lock, so libcosim's worker threads only add synchronization; the exported
  paper platoon ran 100 s in 4.1 s with 0 threads and 14.5 s with libcosim's default, on this loaded
  2-core machine).

What SSP 1.0 cannot say is not silently dropped: ``ssp_notes`` lists it (disturbance pulses, a
Gauss-Seidel master), and the command prints it. The XML is checked against the SSP 1.0 schemas that
FMPy ships (``fmpy/ssp/schema``) in tests/test_ssp.py.
"""

from __future__ import annotations

import dataclasses
import zipfile
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Mapping, Sequence
from xml.etree.ElementTree import Element, SubElement, indent, register_namespace, tostring

from orchestrator.scenario.config import Config
from orchestrator.scenario.scenario import ComponentSpec, Scenario
from orchestrator.support.output import Kind, check_target, replacing

SSD = "http://ssp-standard.org/SSP1/SystemStructureDescription"
SSC = "http://ssp-standard.org/SSP1/SystemStructureCommon"
SSV = "http://ssp-standard.org/SSP1/SystemStructureParameterValues"
OSP = "http://opensimulationplatform.com/SSP/OSPAnnotations"
OSP_ANNOTATION = "com.opensimulationplatform"
FMU_TYPE = "application/x-fmu-sharedlibrary"
SSV_TYPE = "application/x-ssp-parameter-set"
for _prefix, _uri in (("ssd", SSD), ("ssc", SSC), ("ssv", SSV), ("osp", OSP)):
    register_namespace(_prefix, _uri)

_ZIP_TIME = (2020, 1, 1, 0, 0, 0)  # fixed entry times: the same config gives the same bytes


class SspError(ValueError):
    """The package cannot be written as asked (a parameter the FMU does not have)."""


@dataclass(frozen=True)
class FmuInterface:
    """What the .ssd needs from one FMU: its variables (name -> type, causality, unit) and its units."""

    path: Path
    variables: dict[str, tuple[str, str, str | None]]
    units: dict[str, dict[str, int]]

    @classmethod
    def read(cls, path: Path) -> "FmuInterface":
        from fmpy import read_model_description

        description = read_model_description(str(path))
        variables = {v.name: (v.type, v.causality, v.unit) for v in description.modelVariables}
        units = {}
        for unit in description.unitDefinitions:
            base = unit.baseUnit
            exponents = {name: int(getattr(base, name)) for name in ("kg", "m", "s", "A", "K", "mol", "cd", "rad")
                         if base is not None and getattr(base, name, 0)}
            units[unit.name] = exponents
        return cls(Path(path), variables, units)


def _q(namespace: str, tag: str) -> str:
    return f"{{{namespace}}}{tag}"


def ssv_text(kind: str, value: Any) -> str:
    """A parameter value as SSV writes it: shortest exact text for reals, xs:boolean for booleans."""
    if kind == "Real":
        return repr(float(value))
    if kind == "Integer":
        return str(int(value))
    if kind == "Boolean":
        return "true" if value else "false"
    return str(value)


def parameter_set(name: str, parameters: Mapping[str, Any], fmu: FmuInterface) -> bytes:
    """One component's parameter values as an SSV 1.0 document (``ssv:ParameterSet``)."""
    root = Element(_q(SSV, "ParameterSet"), {"version": "1.0", "name": name})
    listed = SubElement(root, _q(SSV, "Parameters"))
    for parameter, value in parameters.items():
        if parameter not in fmu.variables:
            raise SspError(f"{name}: {fmu.path.name} has no parameter {parameter!r}")
        kind = fmu.variables[parameter][0]
        entry = SubElement(listed, _q(SSV, "Parameter"), {"name": parameter})
        SubElement(entry, _q(SSV, kind), {"value": ssv_text(kind, value)})
    indent(root)  # a file people read and diff
    return tostring(root, encoding="UTF-8", xml_declaration=True)


def system_structure(scenario: Scenario, components: Sequence[ComponentSpec], fmus: Mapping[str, FmuInterface],
                     stop_time: float, step: float, worker_threads: int | None = None,
                     name: str = "platoon") -> bytes:
    """The SystemStructure.ssd of ``components`` (kind -> FMU in ``fmus``) wired as ``scenario.connections``."""
    root = Element(_q(SSD, "SystemStructureDescription"),
                   {"name": name, "version": "1.0", "generationTool": "platoon-cosim export-ssp"})
    system = SubElement(root, _q(SSD, "System"), {"name": name})
    elements = SubElement(system, _q(SSD, "Elements"))
    for spec in components:
        fmu = fmus[spec.fmu]
        component = SubElement(elements, _q(SSD, "Component"),
                               {"name": spec.name, "type": FMU_TYPE, "source": f"resources/{fmu.path.name}"})
        connectors = SubElement(component, _q(SSD, "Connectors"))
        for variable, (kind, causality, unit) in fmu.variables.items():
            if causality not in ("input", "output"):
                continue
            connector = SubElement(connectors, _q(SSD, "Connector"), {"name": variable, "kind": causality})
            SubElement(connector, _q(SSC, kind), {"unit": unit} if unit and kind == "Real" else {})
        bindings = SubElement(component, _q(SSD, "ParameterBindings"))
        SubElement(bindings, _q(SSD, "ParameterBinding"), {"type": SSV_TYPE, "source": f"resources/{spec.name}.ssv"})
    connections = SubElement(system, _q(SSD, "Connections"))
    for c in scenario.connections:
        SubElement(connections, _q(SSD, "Connection"), {"startElement": c.source, "startConnector": c.output,
                                                         "endElement": c.destination, "endConnector": c.input})
    units: dict[str, dict[str, int]] = {}
    for kind in sorted({spec.fmu for spec in components}):
        units.update(fmus[kind].units)
    if units:
        unit_list = SubElement(root, _q(SSD, "Units"))
        for unit, exponents in sorted(units.items()):
            node = SubElement(unit_list, _q(SSC, "Unit"), {"name": unit})
            SubElement(node, _q(SSC, "BaseUnit"), {k: str(v) for k, v in exponents.items()})
    experiment = SubElement(root, _q(SSD, "DefaultExperiment"), {"startTime": "0.0", "stopTime": repr(float(stop_time))})
    annotation = SubElement(SubElement(experiment, _q(SSD, "Annotations")), _q(SSC, "Annotation"),
                            {"type": OSP_ANNOTATION})
    algorithm = {"baseStepSize": repr(float(step))}
    if worker_threads is not None:
        algorithm["numWorkerThreads"] = str(worker_threads)
    SubElement(SubElement(annotation, _q(OSP, "Algorithm")), _q(OSP, "FixedStepAlgorithm"), algorithm)
    indent(root)  # a file people read and diff
    return tostring(root, encoding="UTF-8", xml_declaration=True)


def _entry(name: str, compress: bool) -> zipfile.ZipInfo:
    info = zipfile.ZipInfo(name, date_time=_ZIP_TIME)
    info.compress_type = zipfile.ZIP_DEFLATED if compress else zipfile.ZIP_STORED  # an FMU is a zip already
    info.external_attr = 0o644 << 16
    return info


def write_ssp(out: Path, scenario: Scenario, fmu_paths: Mapping[str, Path],
              components: Sequence[ComponentSpec] | None = None, worker_threads: int | None = None,
              force: bool = True) -> Path:
    """Write the SSP package of ``scenario`` to ``out`` (written aside, then moved into place).

    ``components`` replaces the scenario's own (e.g. a live vehicle's LiveVehicle FMU in place of its
    Vehicle); ``fmu_paths`` maps each FMU kind used to its file. Without ``force`` (``--overwrite``) an
    existing ``out`` that is not an SSP package is refused; never a FIFO, device or folder."""
    components = list(scenario.components if components is None else components)
    sim = scenario.config.simulation
    fmus = {kind: FmuInterface.read(fmu_paths[kind]) for kind in sorted({spec.fmu for spec in components})}
    entries: dict[str, tuple[bytes, bool]] = {
        "SystemStructure.ssd": (system_structure(scenario, components, fmus, sim.stop_time, sim.step, worker_threads,
                                                 scenario.config.name or "platoon"), True)}
    for spec in components:
        entries[f"resources/{spec.name}.ssv"] = (parameter_set(spec.name, spec.parameters, fmus[spec.fmu]), True)
    for fmu in fmus.values():
        entries[f"resources/{fmu.path.name}"] = (fmu.path.read_bytes(), False)

    out = Path(out)
    check_target(out, force, fmu_paths.values(), kind=SSP)  # the output rule (support/output.py): OutputError in one line
    with replacing(out) as partial, zipfile.ZipFile(partial, "w") as archive:  # aside, synced, renamed
        for name in sorted(entries):
            data, compress = entries[name]
            archive.writestr(_entry(name, compress), data)
    return out


def is_ssp(path: Path) -> bool:
    """A ``kind`` test (support/output.py): a zip holding SystemStructure.ssd, as ``write_ssp`` writes."""
    try:
        with zipfile.ZipFile(path) as archive:
            return "SystemStructure.ssd" in archive.namelist()
    except (OSError, zipfile.BadZipFile):
        return False


def ssp_notes(config: Config) -> list[str]:
    """What the config asks for that an SSP 1.0 package cannot carry (the command prints these)."""
    notes = []
    if config.disturbance:
        pulses = ", ".join(d.text() for d in config.disturbance)
        notes.append(f"disturbance pulses are not in the package (SSP 1.0 has no input schedules): {pulses}; "
                     "drive the disturbance.* inputs in the importing tool")
    if config.simulation.master != "jacobi":
        notes.append(f"simulation.master = {config.simulation.master!r} is not in the package: libcosim's "
                     "fixed-step algorithm is a Jacobi master")
    return notes


def export_components(config: Config, scenario: Scenario) -> list[ComponentSpec]:
    """The scenario's components, with each live vehicle (``endpoint = "zenoh"``) as a LiveVehicle FMU that
    reaches the robot the config names (its ``hil.*`` parameters), and each remote vehicle (``endpoint =
    "remote"``) as a RemoteVehicle FMU that reaches its ``platoon serve`` (its ``remote.*`` parameters)."""
    live, remote = _live_parameters(config), _remote_parameters(config)
    if not live and not remote:
        return list(scenario.components)
    from fmus.builders import LIVE_FMU, REMOTE_FMU

    def replaced(spec: ComponentSpec) -> ComponentSpec:
        if spec.name in live:
            return ComponentSpec(spec.name, LIVE_FMU, {**spec.parameters, **live[spec.name]})
        if spec.name in remote:
            return ComponentSpec(spec.name, REMOTE_FMU, {**spec.parameters, **remote[spec.name]})
        return spec

    return [replaced(spec) for spec in scenario.components]


def _absolute(path: str | None) -> str | None:
    """A config's Zenoh config file, relative to the folder of the export, not of whoever runs the package."""
    return str(Path(path).resolve()) if path else None


def _live_parameters(config: Config) -> dict[str, dict[str, Any]]:
    """Each live vehicle's ``hil.*`` parameters, by component name ({} without live vehicles)."""
    live = config.live_vehicles()
    if not live:
        return {}
    from fmus.slaves.LiveVehicle import hil_parameters

    from orchestrator.components.live import live_settings
    from orchestrator.scenario.wiring import vehicle_name

    on_ros = [f"vehicles.{k}.ros2" for k in sorted(live) if config.override(k).ros2 is not None]
    if on_ros:
        raise SspError(f"{', '.join(on_ros)}: the LiveVehicle FMU speaks our protocol only, not ROS 2 topics; "
                       "export the config without these tables, or run it with platoon run")
    parameters = {}
    for vehicle in live:
        settings = live_settings(config, vehicle)
        settings = dataclasses.replace(settings, zenoh_config=_absolute(settings.zenoh_config))
        parameters[vehicle_name(vehicle)] = hil_parameters(settings)
    return parameters


def _remote_parameters(config: Config) -> dict[str, dict[str, Any]]:
    """Each remote vehicle's ``remote.*`` parameters (its server, as ``platoon run`` reaches it), by component
    name ({} without remote vehicles)."""
    remote = config.remote_vehicles()
    if not remote:
        return {}
    from fmus.slaves.RemoteVehicle import remote_parameters

    from orchestrator.components.remote import server_name
    from orchestrator.scenario.wiring import vehicle_name

    parameters = {}
    for vehicle in remote:
        override = config.override(vehicle)
        parameters[vehicle_name(vehicle)] = remote_parameters(
            server_name(config, vehicle), override.prefix or config.hil.prefix, tuple(override.connect or ()),
            tuple(override.listen or ()), _absolute(override.zenoh_config), config.remote.step_timeout,
            config.remote.connect_timeout, config.hil.allow_insecure)
    return parameters


def export_ssp(config: Config, out: Path, fmu_dir: Path, force: bool = False, worker_threads: int | None = 0) -> Path:
    """Build the FMUs the config needs (if stale) and write its SSP package to ``out``."""
    from orchestrator.components.kinds import ensure_fmus, resolve_fmu_kind
    from orchestrator.scenario.scenario import build_scenario

    scenario = build_scenario(config)
    components = export_components(config, scenario)
    kinds = tuple(sorted({spec.fmu for spec in components}))
    fmu_paths = ensure_fmus(fmu_dir, resolve_fmu_kind(config.simulation.fmus, fmu_dir), kinds)
    return write_ssp(out, scenario, fmu_paths, components, worker_threads=worker_threads, force=force)


SSP = Kind("an SSP package", is_ssp)  # what `platoon export-ssp` replaces without --overwrite
