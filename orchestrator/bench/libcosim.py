"""libcosim (libcosimpy, the C++ Open Simulation Platform master) on our own FMUs and wiring.

Two set-ups, as issue 10 asks: ``CosimExecution.from_step_size`` with libcosim's default worker
threads, and an SSP file written at run time from our wiring with
``<osp:FixedStepAlgorithm numWorkerThreads="0">`` (every FMU stepped on the calling thread, as ours).
"""

from __future__ import annotations

import shutil
import tempfile
import time
from pathlib import Path
from typing import Any
from xml.sax.saxutils import quoteattr

from fmus.build import DEFAULT_OUT

from .common import BenchError
from .platoon import STEP, fmu_files, scenario_for

NANOSECONDS = 1_000_000_000


def _check(ok: object, what: str) -> None:
    if not ok:
        raise BenchError(f"libcosim: {what} failed")


_SSV = {"Real": "ssv:Real", "Integer": "ssv:Integer", "Boolean": "ssv:Boolean", "String": "ssv:String"}


def _ssv_value(kind: str, value: Any) -> str:
    if kind == "Real":
        return repr(float(value))
    if kind == "Integer":
        return str(int(value))
    if kind == "Boolean":
        return "true" if value else "false"
    return str(value)


def write_ssp(folder: Path, scenario, fmu_paths: dict[str, Path], worker_threads: int | None) -> Path:
    """An SSD (SSP 1.0 system structure) of the scenario: components with their parameters as
    ParameterValues, every connection of the wiring, and the OSP fixed-step algorithm annotation."""
    from fmpy import read_model_description

    folder.mkdir(parents=True, exist_ok=True)
    for path in fmu_paths.values():
        shutil.copy(path, folder / path.name)

    variables = {kind: {v.name: v for v in read_model_description(str(path)).modelVariables}
                 for kind, path in fmu_paths.items()}
    kind_of = {spec.name: spec.fmu for spec in scenario.components}
    connectors: dict[str, dict[str, str]] = {spec.name: {} for spec in scenario.components}
    for c in scenario.connections:
        connectors[c.source][c.output] = "output"
        connectors[c.destination][c.input] = "input"
    lines = [
        '<?xml version="1.0" encoding="UTF-8"?>',
        '<ssd:SystemStructureDescription name="platoon" version="1.0"'
        ' xmlns:ssd="http://ssp-standard.org/SSP1/SystemStructureDescription"'
        ' xmlns:ssc="http://ssp-standard.org/SSP1/SystemStructureCommon"'
        ' xmlns:ssv="http://ssp-standard.org/SSP1/SystemStructureParameterValues"'
        ' xmlns:osp="http://opensimulationplatform.com/SSP/OSPAnnotations">',
        '  <ssd:System name="platoon">',
        '    <ssd:Elements>',
    ]
    for spec in scenario.components:
        lines.append(f'      <ssd:Component name={quoteattr(spec.name)} source={quoteattr(fmu_paths[spec.fmu].name)}>')
        lines.append('        <ssd:Connectors>')
        for name, kind in connectors[spec.name].items():
            lines.append(f'          <ssd:Connector name={quoteattr(name)} kind="{kind}"><ssc:Real/></ssd:Connector>')
        lines.append('        </ssd:Connectors>')
        lines.append('        <ssd:ParameterBindings><ssd:ParameterBinding><ssd:ParameterValues>')
        lines.append('          <ssv:ParameterSet version="1.0" name="initialValues"><ssv:Parameters>')
        for name, value in spec.parameters.items():
            kind = variables[kind_of[spec.name]][name].type
            lines.append(f'            <ssv:Parameter name={quoteattr(name)}><{_SSV[kind]} '
                         f'value={quoteattr(_ssv_value(kind, value))}/></ssv:Parameter>')
        lines.append('          </ssv:Parameters></ssv:ParameterSet>')
        lines.append('        </ssd:ParameterValues></ssd:ParameterBinding></ssd:ParameterBindings>')
        lines.append('      </ssd:Component>')
    lines.append('    </ssd:Elements>')
    lines.append('    <ssd:Connections>')
    for c in scenario.connections:
        lines.append(f'      <ssd:Connection startElement={quoteattr(c.source)} startConnector={quoteattr(c.output)}'
                     f' endElement={quoteattr(c.destination)} endConnector={quoteattr(c.input)}/>')
    lines.append('    </ssd:Connections>')
    lines.append('  </ssd:System>')
    threads = "" if worker_threads is None else f' numWorkerThreads="{worker_threads}"'
    lines += [
        '  <ssd:DefaultExperiment startTime="0.0">',
        '    <ssd:Annotations>',
        '      <ssc:Annotation type="com.opensimulationplatform">',
        f'        <osp:Algorithm><osp:FixedStepAlgorithm baseStepSize="{STEP!r}"{threads}/></osp:Algorithm>',
        '      </ssc:Annotation>',
        '    </ssd:Annotations>',
        '  </ssd:DefaultExperiment>',
        '</ssd:SystemStructureDescription>',
    ]
    path = folder / "SystemStructure.ssd"
    path.write_text("\n".join(lines) + "\n")
    return path


def run_libcosim(n: int, steps: int, from_ssp: bool, coupling: str = "extrapolate",
                 fmu_dir: Path = DEFAULT_OUT) -> dict[str, Any]:
    """libcosim (libcosimpy) on our platoon: default worker threads, or from an SSP file with 0 threads."""
    from libcosimpy.CosimEnums import CosimVariableType
    from libcosimpy.CosimExecution import CosimExecution
    from libcosimpy.CosimLogging import CosimLogLevel, log_output_level
    from libcosimpy.CosimObserver import CosimObserver
    from libcosimpy.CosimSlave import CosimLocalSlave

    log_output_level(CosimLogLevel.ERROR)
    scenario = scenario_for(n, steps, coupling)
    paths = fmu_files(fmu_dir)
    step_ns = int(round(STEP * NANOSECONDS))
    slaves = []
    if from_ssp:
        folder = Path(tempfile.mkdtemp(prefix="bench-ssp-"))
        execution = CosimExecution.from_ssp_file(str(write_ssp(folder, scenario, paths, worker_threads=0)))
    else:
        execution = CosimExecution.from_step_size(step_ns)
        for spec in scenario.components:
            slave = CosimLocalSlave(str(paths[spec.fmu]), spec.name)
            slaves.append(slave)
            _check(execution.add_local_slave(slave) >= 0, f"add {spec.name}")
    index = {spec.name: execution.slave_index_from_instance_name(spec.name) for spec in scenario.components}
    variables = {name: {v.name.decode(): (v.reference, CosimVariableType(v.type)) for v in execution.slave_variables(i)}
                 for name, i in index.items()}
    if not from_ssp:
        setters = {CosimVariableType.REAL: (execution.real_initial_value, float),
                   CosimVariableType.INTEGER: (execution.integer_initial_value, int),
                   CosimVariableType.BOOLEAN: (execution.boolean_initial_value, bool),
                   CosimVariableType.STRING: (execution.string_initial_value, str)}
        for spec in scenario.components:
            for name, value in spec.parameters.items():
                reference, kind = variables[spec.name][name]
                setter, convert = setters[kind]
                _check(setter(index[spec.name], reference, convert(value)), f"set {spec.name}.{name}")
        for c in scenario.connections:
            _check(execution.connect_real_variables(index[c.source], variables[c.source][c.output][0],
                                                    index[c.destination], variables[c.destination][c.input][0]) == 0,
                   f"connect {c}")
    last = CosimObserver.create_last_value()
    _check(execution.add_observer(last), "add the observer")
    _check(execution.step(1), "first step")  # libcosim initializes on its first step: time the other steps - 1
    started, cpu_started = time.perf_counter(), time.process_time()
    _check(execution.step(steps - 1), "stepping")
    elapsed, cpu = time.perf_counter() - started, time.process_time() - cpu_started
    _check(execution.status().current_time == steps * step_ns, "the end time")
    final = {name: last.last_real_values(i, [variables[name]["x"][0], variables[name]["y"][0]])
             for name, i in index.items()}
    return {"seconds": elapsed, "cpu_seconds": cpu, "started": started, "final": {k: list(v) for k, v in final.items()}, "timed_steps": steps - 1}
