"""Cost per FMU-step of our engines and of the peers, on our own FMUs and wiring (issue 10).

The platoon of ``orchestrator.scenario.build_scenario`` (1 virtual target + N vehicles, sine law, the
paper's start, ``orchestrator.wiring.platoon_connections``), Jacobi, steps of 0.01 s, run by:

  native             (a) NativeMaster, the C stepping core, tracing off
  native-buffer          the same, every output row copied into the block buffer and handed to Python
  native-traced      (b) the same, and every row encoded as the trace does (one JSON message per
                         component and point, float repr) and written to a zstd-chunked MCAP file
  native-offload     (b') the same encoding and file, done by a second process on shared-memory blocks
                         (orchestrator.native.offload.OffloadedSink); timed until the file is finished
  python             (c) Master + FmuComponent (FMPy's bound fmi2 functions, ctypes arrays allocated once)
  fmpy-bare          (d) a bare FMPy loop: FMU2Slave setReal / doStep / getReal, value references resolved once
  libcosim           (e) libcosim (libcosimpy), default worker threads (CosimExecution.from_step_size)
  libcosim-0threads  (f) libcosim loaded from an SSP file (written at run time from our wiring) with
                         <osp:FixedStepAlgorithm numWorkerThreads="0">
  slaves             (g) the floor: fmus.slaves.Vehicle / VirtualTarget called directly (set_real,
                         do_step, get_real), no FMI at all

Each measurement runs in a fresh interpreter (so libraries, caches and heap never carry over and a
libcosim teardown cannot disturb the next run); repetitions are interleaved (every engine and N once
per round, engine order rotated each round). Timed: the ``--steps`` communication steps after
initialization (libcosim initializes on its first step, so it is timed from its second step). The
result is the median over rounds of microseconds per FMU-step = wall time / (steps x (N + 1)).
Every run's final positions are compared with the native engine's (``agree``): all masters must
be simulating the same system.

    .venv/bin/python benchmarks/bench_engines.py                       # N = 4, 16, 64; 3 rounds; ~5 min
    .venv/bin/python benchmarks/bench_engines.py --n 4 16 64 256 --rounds 5
    .venv/bin/python benchmarks/bench_engines.py --engines native slaves --n 64

Writes runs/bench/engines-<time>.json (every sample, medians, ratios, versions, machine).
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any, Callable
from xml.sax.saxutils import quoteattr

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

ENGINES = ("native", "native-buffer", "native-traced", "native-offload", "python", "fmpy-bare", "libcosim", "libcosim-0threads", "slaves")
LABELS = {
    "native": "(a) native engine, tracing off",
    "native-buffer": "native engine, rows into the block buffer (no encode)",
    "native-traced": "(b) native engine, every step traced (JSON + MCAP), in process",
    "native-offload": "(b') native engine, every step traced, encoded in a 2nd process",
    "python": "(c) Python engine (Master + FmuComponent)",
    "fmpy-bare": "(d) bare FMPy loop (FMU2Slave)",
    "libcosim": "(e) libcosim, default worker threads",
    "libcosim-0threads": "(f) libcosim from SSP, numWorkerThreads=0",
    "slaves": "(g) floor: slave classes called directly",
}
PAPER_START = {"radial_offset": 5.0, "heading_error": 0.1, "speed_factor": 0.8}
STEP = 0.01
TRACE_BLOCK = 500  # rows per block, as the trace writer's
PROFILE_STEPS = 2000  # simulated 20 s at most per profile process
OFFLOAD_BLOCK = 50  # rows per block handed to the second process: the last block is its tail after the run
NANOSECONDS = 1_000_000_000
AGREEMENT = 1e-6  # m: libcosim's nanosecond grid differs from t_k = k h by ulps, nothing else may differ


# --- the scenario ---------------------------------------------------------------------------------

def scenario_for(n: int, steps: int):
    from orchestrator.config import config_from_mapping
    from orchestrator.scenario import build_scenario

    config = config_from_mapping({
        "name": f"bench-{n}",
        "simulation": {"stop_time": steps * STEP, "step": STEP, "master": "jacobi"},
        "platoon": {"count": n, "law": "sine"},
        "initial": dict(PAPER_START),
    })
    return build_scenario(config)


def fmu_files() -> dict[str, Path]:
    from fmus.build import DEFAULT_OUT, build_fmus

    return {built.name: built.path for built in build_fmus(REPO / DEFAULT_OUT)}


def unpacked_fmus() -> dict[str, Any]:
    from orchestrator.components import UnpackedFmu

    return {name: UnpackedFmu.open(path) for name, path in fmu_files().items()}


def final_positions(names: list[str], outputs: list[dict[str, float]]) -> dict[str, list[float]]:
    return {name: [values["x"], values["y"]] for name, values in zip(names, outputs)}


def routes_of(scenario, inputs: dict[str, list[str]], outputs: dict[str, list[str]]):
    """Per component: (input index, source component index, output index), as Master builds them."""
    index = {spec.name: i for i, spec in enumerate(scenario.components)}
    routes: list[list[tuple[int, int, int]]] = [[] for _ in scenario.components]
    for c in scenario.connections:
        routes[index[c.destination]].append(
            (inputs[c.destination].index(c.input), index[c.source], outputs[c.source].index(c.output)))
    return routes


# --- one measurement per engine (run in a child process) ------------------------------------------

def run_native(n: int, steps: int, mode: str) -> dict[str, Any]:
    from orchestrator.native import NativeComponent, NativeMaster

    scenario = scenario_for(n, steps)
    fmus = unpacked_fmus()
    components = [NativeComponent(s.name, fmus[s.fmu], s.parameters) for s in scenario.components]
    master = NativeMaster(components, scenario.connections, scenario.schedules, "jacobi")
    master.initialize(0.0)
    sink: Callable | None = None
    writer = None
    if mode == "buffer":
        sink = lambda rows: None  # noqa: E731
    elif mode == "traced":
        writer = JsonMcapSink(Path(tempfile.mkdtemp(prefix="bench-trace-")) / "trace.mcap",
                              [(c.name, c.outputs) for c in components])
        sink = writer
    elif mode == "offload":
        from orchestrator.native.offload import OffloadedSink

        trace = Path(tempfile.mkdtemp(prefix="bench-trace-")) / "trace.mcap"
        offloaded = OffloadedSink(JsonMcapSink, (trace, [(c.name, c.outputs) for c in components]),
                                  master.width, OFFLOAD_BLOCK, slots=8)
        sink = offloaded
    started, cpu_started = time.perf_counter(), time.process_time()
    master.run_blocks(STEP, steps, sink, initialize=False, block=OFFLOAD_BLOCK if mode == "offload" else TRACE_BLOCK)
    if writer is not None:
        writer.finish()
    if mode == "offload":
        offloaded.close()  # every block encoded and the file finished
    elapsed, cpu = time.perf_counter() - started, time.process_time() - cpu_started
    names = [c.name for c in components]
    finals = [dict(zip(c.outputs, values)) for c, values in zip(components, master.outputs)]
    result = {"seconds": elapsed, "cpu_seconds": cpu, "final": final_positions(names, finals)}
    if writer is not None:
        result["trace_bytes"] = writer.path.stat().st_size
        result["messages"] = writer.messages
    if mode == "offload":
        result["trace_bytes"] = trace.stat().st_size
        result["offload_waits"] = offloaded.waits
    master.close()
    return result


class JsonMcapSink:
    """What a trace costs: one JSON message per component and point (the trace's template and float
    repr, orchestrator/trace.py), written to an MCAP file with zstd chunks of 1 MiB."""

    def __init__(self, path: Path, components: list[tuple[str, list[str]]]) -> None:
        from mcap.writer import CompressionType, Writer

        self.path = path
        self._file = open(path, "wb")
        self._writer = Writer(self._file, compression=CompressionType.ZSTD, chunk_size=1 << 20)
        self._writer.start(profile="", library="platoon-cosim bench")
        self._channels, self._templates, self._slices = [], [], []
        offset = 0
        for name, outputs in components:
            keys = ["t", *outputs]
            schema = self._writer.register_schema(name=f"platoon.{name}", encoding="jsonschema", data=json.dumps(
                {"type": "object", "properties": {k: {"type": "number"} for k in keys}}).encode())
            self._channels.append(self._writer.register_channel(topic=f"/platoon/{name}", message_encoding="json",
                                                                schema_id=schema))
            self._templates.append("{" + ",".join(json.dumps(k).replace("%", "%%") + ":%s" for k in keys) + "}")
            self._slices.append((1 + offset, 1 + offset + len(outputs)))
            offset += len(outputs)
        self.messages = 0
        self._sequence = 0

    def __call__(self, rows) -> None:
        write = self._writer.add_message
        text = float.__repr__
        parts = list(zip(self._channels, self._templates, self._slices))
        for row in rows.tolist():
            t = row[0]
            stamp = int(round(t * 1e9))
            head = text(t)
            for channel, template, (a, b) in parts:
                data = (template % (head, *map(text, row[a:b]))).encode()
                write(channel_id=channel, log_time=stamp, publish_time=stamp, sequence=self._sequence, data=data)
            self._sequence += 1
        self.messages += len(rows) * len(parts)

    def finish(self) -> None:
        self._writer.finish()
        self._file.close()


def run_python(n: int, steps: int) -> dict[str, Any]:
    from orchestrator.components import FmuComponent
    from orchestrator.master import Master

    scenario = scenario_for(n, steps)
    fmus = unpacked_fmus()
    components = [FmuComponent(s.name, fmus[s.fmu], s.parameters) for s in scenario.components]
    master = Master(components, scenario.connections, scenario.schedules, "jacobi")
    master.initialize(0.0)

    def observer(t: float, outputs: list[list[float]]) -> None:
        pass

    started, cpu_started = time.perf_counter(), time.process_time()
    for k in range(steps):  # Master.run's loop, with a no-op observer (tracing off)
        master.time = k * STEP
        following = (k + 1) * STEP
        outputs = master.step(following - master.time)
        master.time = following
        observer(master.time, outputs)
    elapsed, cpu = time.perf_counter() - started, time.process_time() - cpu_started
    finals = [dict(zip(c.outputs, values)) for c, values in zip(components, master.outputs)]
    result = {"seconds": elapsed, "cpu_seconds": cpu, "final": final_positions([c.name for c in components], finals)}
    master.close()
    return result


def _grouped_parameters(fmu, parameters: dict[str, Any]) -> dict[str, tuple[list[int], list[Any]]]:
    variables = fmu.variables()
    groups: dict[str, tuple[list[int], list[Any]]] = {}
    for name, value in parameters.items():
        refs, values = groups.setdefault(variables[name].type, ([], []))
        refs.append(variables[name].valueReference)
        values.append(value)
    return groups


def run_fmpy_bare(n: int, steps: int) -> dict[str, Any]:
    from fmpy.fmi2 import FMU2Slave

    scenario = scenario_for(n, steps)
    fmus = unpacked_fmus()
    slaves, in_refs, out_refs, inputs = [], [], [], []
    names = {s.name: s for s in scenario.components}
    in_names, out_names = {}, {}
    for spec in scenario.components:
        fmu = fmus[spec.fmu]
        variables = fmu.variables()
        in_names[spec.name] = [v.name for v in fmu.description.modelVariables if v.causality == "input"]
        out_names[spec.name] = [v.name for v in fmu.description.modelVariables if v.causality == "output"]
        in_refs.append([variables[v].valueReference for v in in_names[spec.name]])
        out_refs.append([variables[v].valueReference for v in out_names[spec.name]])
        starts = fmu.start_values()
        inputs.append([float(starts[v]) for v in in_names[spec.name]])
        slave = FMU2Slave(guid=fmu.guid, unzipDirectory=str(fmu.directory),
                          modelIdentifier=fmu.description.coSimulation.modelIdentifier, instanceName=spec.name)
        slave.instantiate()
        slave.setupExperiment(startTime=0.0)
        setters = {"Real": slave.setReal, "Integer": slave.setInteger, "Boolean": slave.setBoolean,
                   "String": slave.setString}
        for kind, (refs, values) in _grouped_parameters(fmu, spec.parameters).items():
            setters[kind](refs, values)
        slave.enterInitializationMode()
        slaves.append(slave)
    routes = routes_of(scenario, in_names, out_names)
    count = len(slaves)
    outputs = [slaves[c].getReal(out_refs[c]) for c in range(count)]
    for _ in range(count + 2):  # the same settle sweeps as every master here
        for c in range(count):
            for i, source, o in routes[c]:
                inputs[c][i] = outputs[source][o]
            slaves[c].setReal(in_refs[c], inputs[c])
            outputs[c] = slaves[c].getReal(out_refs[c])
    for slave in slaves:
        slave.exitInitializationMode()
    outputs = [slaves[c].getReal(out_refs[c]) for c in range(count)]
    started, cpu_started = time.perf_counter(), time.process_time()
    for k in range(steps):
        t = k * STEP
        h = (k + 1) * STEP - t
        for c in range(count):
            vector = inputs[c]
            for i, source, o in routes[c]:
                vector[i] = outputs[source][o]
            slaves[c].setReal(in_refs[c], vector)
        for slave in slaves:
            slave.doStep(t, h)
        outputs = [slaves[c].getReal(out_refs[c]) for c in range(count)]
    elapsed, cpu = time.perf_counter() - started, time.process_time() - cpu_started
    finals = [dict(zip(out_names[s.name], values)) for s, values in zip(scenario.components, outputs)]
    for slave in slaves:  # free the instances, keep the libraries loaded (see FmuComponent.close)
        slave.fmi2Terminate(slave.component)
        slave.fmi2FreeInstance(slave.component)
    del names
    return {"seconds": elapsed, "cpu_seconds": cpu, "final": final_positions([s.name for s in scenario.components], finals)}


class SlavePlatoon:
    """The floor: the pythonfmu slave classes of our FMUs, instantiated and initialized directly."""

    def __init__(self, n: int, steps: int) -> None:
        from fmus.slaves.Vehicle import Vehicle
        from fmus.slaves.VirtualTarget import VirtualTarget

        classes = {"Vehicle": Vehicle, "VirtualTarget": VirtualTarget}
        self.scenario = scenario = scenario_for(n, steps)
        fmus = unpacked_fmus()
        self.slaves, self.in_refs, self.out_refs, self.inputs, in_names, self.out_names = [], [], [], [], {}, {}
        for spec in scenario.components:
            fmu = fmus[spec.fmu]
            slave = classes[spec.fmu](instance_name=spec.name, resources=str(fmu.directory / "resources"))
            refs = {variable.name: vr for vr, variable in slave.vars.items()}
            in_names[spec.name] = [v.name for v in fmu.description.modelVariables if v.causality == "input"]
            self.out_names[spec.name] = [v.name for v in fmu.description.modelVariables if v.causality == "output"]
            self.in_refs.append([refs[v] for v in in_names[spec.name]])
            self.out_refs.append([refs[v] for v in self.out_names[spec.name]])
            starts = fmu.start_values()
            self.inputs.append([float(starts[v]) for v in in_names[spec.name]])
            slave.setup_experiment(0.0, None, None)
            setters = {"Real": slave.set_real, "Integer": slave.set_integer, "Boolean": slave.set_boolean,
                       "String": slave.set_string}
            variables = fmu.variables()
            for kind, (_, values) in _grouped_parameters(fmu, spec.parameters).items():
                names = [name for name in spec.parameters if variables[name].type == kind]
                setters[kind]([refs[name] for name in names], values)
            slave.enter_initialization_mode()
            self.slaves.append(slave)
        self.routes = routes_of(scenario, in_names, self.out_names)
        slaves, count = self.slaves, len(self.slaves)
        outputs = [slaves[c].get_real(self.out_refs[c]) for c in range(count)]
        for _ in range(count + 2):  # the same settle sweeps as every master here
            for c in range(count):
                for i, source, o in self.routes[c]:
                    self.inputs[c][i] = outputs[source][o]
                slaves[c].set_real(self.in_refs[c], self.inputs[c])
                outputs[c] = slaves[c].get_real(self.out_refs[c])
        for slave in slaves:
            slave.exit_initialization_mode()
        self.outputs = [slaves[c].get_real(self.out_refs[c]) for c in range(count)]
        self.k = 0

    def run(self, steps: int) -> None:
        slaves, inputs, routes, in_refs, out_refs = self.slaves, self.inputs, self.routes, self.in_refs, self.out_refs
        count = len(slaves)
        outputs = self.outputs
        for k in range(self.k, self.k + steps):
            t = k * STEP
            h = (k + 1) * STEP - t
            for c in range(count):
                vector = inputs[c]
                for i, source, o in routes[c]:
                    vector[i] = outputs[source][o]
                slaves[c].set_real(in_refs[c], vector)
            for slave in slaves:
                if not slave.do_step(t, h):
                    raise RuntimeError(f"{slave.instance_name}: do_step failed at t = {t}")
            outputs = [slaves[c].get_real(out_refs[c]) for c in range(count)]
        self.outputs = outputs
        self.k += steps

    def run_split(self, steps: int) -> dict[str, float]:
        """The same loop, each phase timed separately: seconds in transfer, set_real, do_step, get_real."""
        clock = time.perf_counter
        slaves, inputs, routes, in_refs, out_refs = self.slaves, self.inputs, self.routes, self.in_refs, self.out_refs
        count = len(slaves)
        outputs = self.outputs
        spent = dict.fromkeys(("transfer", "set_real", "do_step", "get_real"), 0.0)
        for k in range(self.k, self.k + steps):
            t = k * STEP
            h = (k + 1) * STEP - t
            for c in range(count):
                a = clock()
                vector = inputs[c]
                for i, source, o in routes[c]:
                    vector[i] = outputs[source][o]
                b = clock()
                slaves[c].set_real(in_refs[c], vector)
                spent["transfer"] += b - a
                spent["set_real"] += clock() - b
            for slave in slaves:
                a = clock()
                slave.do_step(t, h)
                spent["do_step"] += clock() - a
            a = clock()
            outputs = [slaves[c].get_real(out_refs[c]) for c in range(count)]
            spent["get_real"] += clock() - a
        self.outputs = outputs
        self.k += steps
        return spent


def run_slaves(n: int, steps: int) -> dict[str, Any]:
    platoon = SlavePlatoon(n, steps)
    started, cpu_started = time.perf_counter(), time.process_time()
    platoon.run(steps)
    elapsed, cpu = time.perf_counter() - started, time.process_time() - cpu_started
    names = [s.name for s in platoon.scenario.components]
    finals = [dict(zip(platoon.out_names[name], values)) for name, values in zip(names, platoon.outputs)]
    return {"seconds": elapsed, "cpu_seconds": cpu, "final": final_positions(names, finals)}


# --- libcosim ---------------------------------------------------------------------------------------

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


def run_libcosim(n: int, steps: int, from_ssp: bool) -> dict[str, Any]:
    from libcosimpy.CosimEnums import CosimVariableType
    from libcosimpy.CosimExecution import CosimExecution
    from libcosimpy.CosimLogging import CosimLogLevel, log_output_level
    from libcosimpy.CosimObserver import CosimObserver
    from libcosimpy.CosimSlave import CosimLocalSlave

    log_output_level(CosimLogLevel.ERROR)
    scenario = scenario_for(n, steps)
    paths = fmu_files()
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
            assert execution.add_local_slave(slave) >= 0
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
                assert setter(index[spec.name], reference, convert(value)), f"{spec.name}.{name}"
        for c in scenario.connections:
            assert execution.connect_real_variables(index[c.source], variables[c.source][c.output][0],
                                                    index[c.destination], variables[c.destination][c.input][0]) == 0
    last = CosimObserver.create_last_value()
    assert execution.add_observer(last)
    assert execution.step(1)  # libcosim initializes on its first step: time the other steps - 1
    started, cpu_started = time.perf_counter(), time.process_time()
    assert execution.step(steps - 1)
    elapsed, cpu = time.perf_counter() - started, time.process_time() - cpu_started
    assert execution.status().current_time == steps * step_ns
    final = {name: last.last_real_values(i, [variables[name]["x"][0], variables[name]["y"][0]])
             for name, i in index.items()}
    return {"seconds": elapsed, "cpu_seconds": cpu, "final": {k: list(v) for k, v in final.items()}, "timed_steps": steps - 1}


def child(engine: str, n: int, steps: int, rounds: int = 3) -> None:
    if engine == "profile":
        sys.stdout.write("RESULT " + json.dumps(profile(n, steps, rounds)) + "\n")
        sys.stdout.flush()
        os._exit(0)
    runners = {
        "native": lambda: run_native(n, steps, "off"),
        "native-buffer": lambda: run_native(n, steps, "buffer"),
        "native-traced": lambda: run_native(n, steps, "traced"),
        "native-offload": lambda: run_native(n, steps, "offload"),
        "python": lambda: run_python(n, steps),
        "fmpy-bare": lambda: run_fmpy_bare(n, steps),
        "libcosim": lambda: run_libcosim(n, steps, from_ssp=False),
        "libcosim-0threads": lambda: run_libcosim(n, steps, from_ssp=True),
        "slaves": lambda: run_slaves(n, steps),
    }
    result = runners[engine]()
    timed = result.setdefault("timed_steps", steps)
    result.update(engine=engine, n=n, steps=steps, us_per_fmu_step=result["seconds"] / (timed * (n + 1)) * 1e6,
                  cpu_us_per_fmu_step=result["cpu_seconds"] / (timed * (n + 1)) * 1e6)
    sys.stdout.write("RESULT " + json.dumps(result) + "\n")
    sys.stdout.flush()
    # pythonfmu leaves objects in this interpreter; its teardown can corrupt the heap (tests/conftest.py)
    os._exit(0)


# --- where the native engine's time goes ------------------------------------------------------------

def _perf_report(data: Path, sort: str, limit: int) -> list[tuple[float, str]]:
    report = subprocess.run(["perf", "report", "-i", str(data), "--stdio", "--no-children", "--sort", sort, "-g", "none"],
                            capture_output=True, text=True)
    rows = []
    for line in report.stdout.splitlines():
        line = line.strip()
        if not line or line.startswith("#") or "%" not in line:
            continue
        share, _, rest = line.partition("%")
        try:
            rows.append((float(share), " ".join(rest.split())))
        except ValueError:
            continue
    return rows[:limit]


def profile(n: int, steps: int, rounds: int) -> dict[str, Any]:
    """In one process: the native loop against the floor (interleaved), the floor's phases, and perf's
    split of the native loop by shared object and symbol (when perf is installed)."""
    from orchestrator.native import NativeComponent, NativeMaster

    # Both platoons run rounds + 1 (floor) and rounds + 2 (native) samples one after the other: keep
    # that within 20 s of simulated time (a 64-vehicle platoon on the paper's circle loses string
    # stability and fails after about 28 s).
    steps = min(steps, PROFILE_STEPS // (rounds + 2))
    scenario = scenario_for(n, steps * (rounds + 2))
    fmus = unpacked_fmus()
    master = NativeMaster([NativeComponent(s.name, fmus[s.fmu], s.parameters) for s in scenario.components],
                          scenario.connections)
    master.initialize(0.0)
    floor = SlavePlatoon(n, steps)
    fmu_steps = steps * (n + 1)
    native_us, floor_us = [], []
    k = 0
    for _ in range(rounds):
        started = time.perf_counter()
        master._core.run(0.0, STEP, k, k + steps)
        native_us.append((time.perf_counter() - started) / fmu_steps * 1e6)
        k += steps
        started = time.perf_counter()
        floor.run(steps)
        floor_us.append((time.perf_counter() - started) / fmu_steps * 1e6)
    spent = floor.run_split(steps)
    clock = time.perf_counter
    started = clock()
    for _ in range(4 * fmu_steps):  # what timing one phase costs
        clock()
    timer_us = (clock() - started) / (4 * fmu_steps) * 1e6
    result: dict[str, Any] = {
        "n": n, "steps": steps, "rounds": rounds,
        "native_us": statistics.median(native_us), "floor_us": statistics.median(floor_us),
        "native_samples": native_us, "floor_samples": floor_us,
        "floor_phases_us": {phase: seconds / fmu_steps * 1e6 for phase, seconds in spent.items()},
        "timer_us_per_call": timer_us,
    }
    if shutil.which("perf"):
        data = Path(tempfile.mkdtemp(prefix="bench-perf-")) / "perf.data"
        recorder = subprocess.Popen(["perf", "record", "-F", "1999", "-p", str(os.getpid()), "-o", str(data)],
                                    stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        time.sleep(0.5)  # perf attaches
        master._core.run(0.0, STEP, k, k + 2 * steps)
        recorder.send_signal(2)
        recorder.wait(timeout=60)
        result["perf_dso"] = _perf_report(data, "dso", 12)
        result["perf_symbols"] = _perf_report(data, "dso,sym", 25)
    master.close()
    return result


def print_profile(result: dict[str, Any]) -> None:
    n = result["n"]
    print(f"N = {n}, {result['steps']} steps per sample, {result['rounds']} interleaved samples, one process:")
    print(f"  native engine loop           {result['native_us']:6.2f} µs per FMU-step")
    print(f"  slave classes called directly {result['floor_us']:6.2f} µs per FMU-step (the floor)")
    print(f"  difference                   {result['native_us'] - result['floor_us']:6.2f} µs: the FMI boundary "
          f"(pythonfmu's C++ wrapper, GIL state, its log buffer) and our loop, minus the floor's Python transfer")
    phases = result["floor_phases_us"]
    print("  the floor by phase (µs per FMU-step, each including ~%.2f µs of timer): " % result["timer_us_per_call"]
          + ", ".join(f"{phase} {value:.2f}" for phase, value in phases.items()))
    if "perf_dso" in result:
        print("  perf, native loop, by shared object: " + ", ".join(f"{name} {share:.1f} %" for share, name in result["perf_dso"]))
        print("  perf, top symbols:")
        for share, name in result["perf_symbols"][:15]:
            print(f"    {share:5.1f} %  {name}")


# --- the driver ---------------------------------------------------------------------------------------

def measure(engine: str, n: int, steps: int) -> dict[str, Any]:
    process = subprocess.run([sys.executable, __file__, "--child", engine, str(n), "--steps", str(steps)],
                             capture_output=True, text=True, cwd=REPO, timeout=3600)
    for line in process.stdout.splitlines():
        if line.startswith("RESULT "):
            return json.loads(line[len("RESULT "):])
    raise RuntimeError(f"{engine} N={n} failed (exit {process.returncode}):\n{process.stdout[-2000:]}\n{process.stderr[-4000:]}")


def versions() -> dict[str, str]:
    import fmpy
    import pythonfmu

    found = {"python": platform.python_version(), "fmpy": fmpy.__version__, "pythonfmu": pythonfmu.__version__}
    try:
        from importlib.metadata import version

        found["libcosimpy"] = version("libcosimpy")
    except Exception:
        pass
    return found


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--n", type=int, nargs="+", default=[4, 16, 64], help="vehicle counts (default 4 16 64)")
    parser.add_argument("--steps", type=int, default=1000, help="communication steps of 0.01 s (default 1000)")
    parser.add_argument("--rounds", type=int, default=3, help="interleaved repetitions (default 3)")
    parser.add_argument("--engines", nargs="+", default=list(ENGINES), choices=ENGINES)
    parser.add_argument("--out", type=Path, default=None, help="JSON results (default runs/bench/engines-<time>.json)")
    parser.add_argument("--profile", action="store_true",
                        help="instead: where the native engine's time goes (native vs floor in one process, "
                             "the floor's phases, perf by shared object), for each --n")
    parser.add_argument("--child", nargs=2, metavar=("ENGINE", "N"), help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.child:
        child(args.child[0], int(args.child[1]), args.steps, args.rounds)
        return
    if args.profile:
        fmu_files()
        results = []
        for n in args.n:
            process = subprocess.run([sys.executable, __file__, "--child", "profile", str(n), "--steps", str(args.steps),
                                      "--rounds", str(args.rounds)], capture_output=True, text=True, cwd=REPO)
            line = next((l for l in process.stdout.splitlines() if l.startswith("RESULT ")), None)
            if line is None:
                raise RuntimeError(f"profile N={n} failed:\n{process.stdout[-2000:]}\n{process.stderr[-4000:]}")
            results.append(json.loads(line[len("RESULT "):]))
            print_profile(results[-1])
        out = args.out or REPO / "runs" / "bench" / f"profile-{time.strftime('%Y%m%d-%H%M%S')}.json"
        out.parent.mkdir(parents=True, exist_ok=True)
        out.write_text(json.dumps({"command": " ".join([Path(sys.executable).name, *sys.argv]), "profiles": results,
                                   "versions": versions()}, indent=1))
        print(f"results: {out}")
        return

    fmu_files()  # build once, before any child needs them
    samples: list[dict[str, Any]] = []
    started = time.perf_counter()
    for round_ in range(args.rounds):
        for n in args.n:
            shift = round_ % len(args.engines)
            for engine in args.engines[shift:] + args.engines[:shift]:
                result = measure(engine, n, args.steps)
                result["round"] = round_
                samples.append(result)
                print(f"round {round_ + 1}/{args.rounds}  N={n:<4} {engine:<18} {result['us_per_fmu_step']:8.2f} µs/FMU-step",
                      flush=True)
    elapsed = time.perf_counter() - started

    medians: dict[str, dict[int, float]] = {}
    cpu_medians: dict[str, dict[int, float]] = {}
    for engine in args.engines:
        for n in args.n:
            mine = [s for s in samples if s["engine"] == engine and s["n"] == n]
            medians.setdefault(engine, {})[n] = statistics.median(s["us_per_fmu_step"] for s in mine)
            cpu_medians.setdefault(engine, {})[n] = statistics.median(s["cpu_us_per_fmu_step"] for s in mine)
    agree: dict[str, dict[int, float]] = {}
    if "native" in args.engines:
        for engine in args.engines:
            for n in args.n:
                reference = next(s for s in samples if s["engine"] == "native" and s["n"] == n)
                worst = 0.0
                for s in samples:
                    if s["engine"] != engine or s["n"] != n:
                        continue
                    for name, values in s["final"].items():
                        worst = max(worst, *(abs(a - b) for a, b in zip(values, reference["final"][name])))
                agree.setdefault(engine, {})[n] = worst

    def ratio(a: str, b: str) -> dict[int, float] | None:
        if a in medians and b in medians:
            return {n: medians[a][n] / medians[b][n] for n in args.n}
        return None

    ratios = {
        "native / libcosim-0threads (floor <= 1.0)": ratio("native", "libcosim-0threads"),
        "native-traced / native (floor <= 1.2)": ratio("native-traced", "native"),
        "native-offload / native (floor <= 1.2)": ratio("native-offload", "native"),
        "python / fmpy-bare (floor <= 0.8)": ratio("python", "fmpy-bare"),
        "native / slaves (overhead over the floor)": ratio("native", "slaves"),
        "native-buffer / native": ratio("native-buffer", "native"),
    }
    flatness = {engine: max(by_n.values()) / min(by_n.values()) for engine, by_n in medians.items()}

    print()
    print(f"µs per FMU-step, median of {args.rounds} interleaved rounds, {args.steps} steps of {STEP} s, Jacobi, "
          f"1 target + N vehicles")
    print("| engine | " + " | ".join(f"N={n}" for n in args.n) + " | max/min over N | CPU time: " +
          " | ".join(f"N={n}" for n in args.n) + " |")
    print("|---|" + "---|" * (2 * len(args.n) + 1))
    for engine in args.engines:
        cells = " | ".join(f"{medians[engine][n]:.1f}" for n in args.n)
        cpu_cells = " | ".join(f"{cpu_medians[engine][n]:.1f}" for n in args.n)
        print(f"| {LABELS[engine]} | {cells} | {flatness[engine]:.2f} | {cpu_cells} |")
    print()
    for name, values in ratios.items():
        if values is not None:
            print(f"{name}: " + ", ".join(f"N={n}: {v:.3f}" for n, v in values.items()))
    if agree:
        print("largest |final position - native| per engine: " + ", ".join(
            f"{engine}: {max(by_n.values()):.1e} m" for engine, by_n in agree.items() if engine in agree))
    print(f"(measured in {elapsed:.0f} s)")

    out = args.out or REPO / "runs" / "bench" / f"engines-{time.strftime('%Y%m%d-%H%M%S')}.json"
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps({
        "command": " ".join([Path(sys.executable).name, *sys.argv]),
        "steps": args.steps, "step": STEP, "rounds": args.rounds, "n": args.n, "master": "jacobi",
        "unit": "microseconds per FMU-step (wall time / (steps x (N + 1)))",
        "medians": medians, "cpu_medians": cpu_medians, "ratios": {k: v for k, v in ratios.items() if v is not None},
        "flatness_max_over_min": flatness, "final_position_agreement_m": agree,
        "versions": versions(), "machine": {"platform": platform.platform(), "cpus": os.cpu_count(),
                                            "processor": platform.processor()},
        "samples": samples, "seconds": elapsed,
    }, indent=1))
    print(f"results: {out}")
    bad = {engine: value for engine, by_n in agree.items() for value in by_n.values() if value > AGREEMENT}
    if bad:
        print(f"warning: engines disagree with the native engine by more than {AGREEMENT} m: {bad}", file=sys.stderr)


if __name__ == "__main__":
    main()
