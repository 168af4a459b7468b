"""One timed run of the benchmark platoon per engine; each runs in its own child process.

  native             (a) NativeMaster, the C stepping core, tracing off
  native-buffer          the same, every output row copied into the block buffer and handed to Python
  native-traced      (b) the same, every row written by the run's trace writer in process
                         (TraceWriter, every channel: components, errors, Foxglove), until the file is finished
  native-offload     (b') the same file written by the trace writer process (TraceWorker, what
                         `--trace-writer process` runs), timed until the worker finished the file
  python             (c) Master + FmuComponent (FMPy's bound fmi2 functions, ctypes arrays allocated once)
  fmpy-bare          (d) a bare FMPy loop: FMU2Slave setReal / doStep / getReal, value references resolved once
  libcosim           (e) libcosim (libcosimpy), default worker threads (CosimExecution.from_step_size)
  libcosim-0threads  (f) libcosim loaded from an SSP file (written at run time from our wiring) with
                         <osp:FixedStepAlgorithm numWorkerThreads="0">; no observer while timed (libcosim
                         records nothing, as our engines with tracing off)
  libcosim-0threads-lastvalue  the same with libcosim's last-value observer while timed (reads every
                         variable after each step): the baseline this suite used first, kept to show its cost
  slaves             (g) the floor: fmus.slaves.Vehicle / VirtualTarget called directly, no FMI at all

Timed: the communication steps after initialization (libcosim initializes on its first step, so it
is timed from its second). Every run reports its final positions, so that the suite can check that
all masters simulated the same system.
"""

from __future__ import annotations

import gc
import tempfile
import time
from pathlib import Path
from typing import Any, Callable

from fmus.builders import DEFAULT_OUT

from orchestrator.components.fmu import parameters_by_type
from .common import rss_kib
from .platoon import STEP, causal_names, final_positions, routes_of, scenario_for, unpacked_fmus

LABELS = {
    "native": "(a) native engine, tracing off",
    "native-buffer": "native engine, rows into the block buffer (no encode)",
    "native-traced": "(b) native engine, every step traced, trace encoded in process",
    "native-offload": "(b') native engine, every step traced, trace encoded by a 2nd process",
    "python": "(c) Python engine (Master + FmuComponent)",
    "fmpy-bare": "(d) bare FMPy loop (FMU2Slave)",
    "libcosim": "(e) libcosim, default worker threads",
    "libcosim-0threads": "(f) libcosim from SSP, numWorkerThreads=0, no observer",
    "libcosim-0threads-lastvalue": "libcosim from SSP, 0 threads, last-value observer",
    "slaves": "(g) floor: slave classes called directly",
}
# every engine the per-FMU-step suites know (`platoon bench steps --engines`; the CLI lists the same names)
ENGINES = ("native", "native-buffer", "native-traced", "native-offload", "python", "fmpy-bare", "libcosim",
           "libcosim-0threads", "libcosim-0threads-lastvalue", "slaves")
LIBCOSIM_ENGINES = ("libcosim", "libcosim-0threads", "libcosim-0threads-lastvalue")


_collected_at: list[float] = []  # perf_counter() at the start of every garbage collection in this process


def _note_collection(phase: str, info: dict[str, Any]) -> None:
    if phase == "start":
        _collected_at.append(time.perf_counter())


def run_native(n: int, steps: int, mode: str, coupling: str, fmu_dir: Path) -> dict[str, Any]:
    """The native engine; ``mode``: "" (no trace), "buffer", "traced" (in process) or "offload" (2nd process),
    with the blocks, block sizes and trace writers that ``run_scenario`` uses."""
    from orchestrator.execution.native import NativeComponent, NativeMaster
    from orchestrator.execution.run import open_trace_writer
    from orchestrator.trace.format import BLOCK
    from orchestrator.trace.worker import WORKER_BLOCK

    scenario = scenario_for(n, steps, coupling)
    fmus = unpacked_fmus(fmu_dir)
    components = [NativeComponent(s.name, fmus[s.fmu], s.parameters) for s in scenario.components]
    outputs = [(c.name, list(c.outputs)) for c in components]
    trace = Path(tempfile.mkdtemp(prefix="bench-trace-")) / "trace.mcap"
    writer: Any = None
    if mode in ("traced", "offload"):  # created before the FMUs are instantiated, as run_scenario does
        writer = open_trace_writer("process" if mode == "offload" else "inline", trace, outputs, None, scenario.config,
                                   native=True)  # the C encoder, as run_scenario's native engine
    master = NativeMaster(components, scenario.connections, scenario.schedules, "jacobi")
    master.initialize(0.0)
    sink: Callable | None = None
    if mode == "buffer":
        sink = lambda rows: None  # noqa: E731
    elif writer is not None:
        sink = writer.write_block
    started, cpu_started = time.perf_counter(), time.process_time()
    master.run_blocks(STEP, steps, sink, initialize=False, block=WORKER_BLOCK if mode == "offload" else BLOCK,
                      deliver_interval=0.5)
    if writer is not None:
        writer.close()  # every row encoded and the file finished (by the worker, for "offload")
    elapsed, cpu = time.perf_counter() - started, time.process_time() - cpu_started
    names = [c.name for c in components]
    finals = [dict(zip(c.outputs, values)) for c, values in zip(components, master.outputs)]
    result = {"seconds": elapsed, "cpu_seconds": cpu, "started": started, "final": final_positions(names, finals)}
    if writer is not None:
        result["trace_bytes"] = trace.stat().st_size
    master.close()
    return result


def step_python_master(master: Any, first: int, stop: int,
                       observer: Callable[[float, list[list[float]]], None] | None = None) -> None:
    """Master.run's loop over steps ``first`` to ``stop - 1`` of 0.01 s, after initialization."""
    for k in range(first, stop):
        master.time = k * STEP
        following = (k + 1) * STEP
        outputs = master.step(following - master.time)
        master.time = following
        if observer is not None:
            observer(master.time, outputs)


def run_python(n: int, steps: int, coupling: str, fmu_dir: Path) -> dict[str, Any]:
    from orchestrator.components.fmu import FmuComponent
    from orchestrator.execution.python_master import Master

    scenario = scenario_for(n, steps, coupling)
    fmus = unpacked_fmus(fmu_dir)
    components = [FmuComponent(s.name, fmus[s.fmu], s.parameters) for s in scenario.components]
    master = Master(components, scenario.connections, scenario.schedules, "jacobi")
    master.initialize(0.0)

    def observer(t: float, outputs: list[list[float]]) -> None:
        pass

    started, cpu_started = time.perf_counter(), time.process_time()
    step_python_master(master, 0, steps, observer)  # a no-op observer: tracing off
    elapsed, cpu = time.perf_counter() - started, time.process_time() - cpu_started
    finals = [dict(zip(c.outputs, values)) for c, values in zip(components, master.outputs)]
    result = {"seconds": elapsed, "cpu_seconds": cpu, "started": started, "final": final_positions([c.name for c in components], finals)}
    master.close()
    return result


def fmpy_bare_platoon(n: int, steps: int, coupling: str, fmu_dir: Path) -> tuple[Any, list[Any], dict[str, list[str]]]:
    """The bare FMPy loop, initialized: a ``DirectLoop`` over FMPy's ``FMU2Slave`` setReal / doStep /
    getReal (value references resolved once), its slaves, and each component's output names."""
    from fmpy.fmi2 import FMU2Slave

    from .floor import DirectLoop

    scenario = scenario_for(n, steps, coupling)
    fmus = unpacked_fmus(fmu_dir)
    slaves, in_refs, out_refs, inputs = [], [], [], []
    in_names, out_names = {}, {}
    for spec in scenario.components:
        fmu = fmus[spec.fmu]
        variables = fmu.variables()
        in_names[spec.name] = causal_names(fmu, "input")
        out_names[spec.name] = causal_names(fmu, "output")
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
        for kind, (refs, values) in parameters_by_type(variables, spec.parameters).items():
            setters[kind](refs, values)
        slave.enterInitializationMode()
        slaves.append(slave)
    loop = DirectLoop([s.setReal for s in slaves], [s.doStep for s in slaves], [s.getReal for s in slaves],
                      in_refs, out_refs, inputs, routes_of(scenario, in_names, out_names),
                      [s.name for s in scenario.components])
    loop.settle()
    for slave in slaves:
        slave.exitInitializationMode()
    loop.refresh()
    return loop, slaves, out_names


def free_fmpy_slaves(slaves: list[Any]) -> None:
    """Free the instances, keep the libraries loaded (see FmuComponent.close)."""
    for slave in slaves:
        slave.fmi2Terminate(slave.component)
        slave.fmi2FreeInstance(slave.component)


def run_fmpy_bare(n: int, steps: int, coupling: str, fmu_dir: Path) -> dict[str, Any]:
    loop, slaves, out_names = fmpy_bare_platoon(n, steps, coupling, fmu_dir)
    started, cpu_started = time.perf_counter(), time.process_time()
    loop.run(steps)
    elapsed, cpu = time.perf_counter() - started, time.process_time() - cpu_started
    free_fmpy_slaves(slaves)
    return {"seconds": elapsed, "cpu_seconds": cpu, "started": started, "final": loop.finals(out_names)}


def run_slaves(n: int, steps: int, coupling: str, fmu_dir: Path) -> dict[str, Any]:
    from .floor import SlavePlatoon

    platoon = SlavePlatoon(n, steps, coupling, fmu_dir)
    started, cpu_started = time.perf_counter(), time.process_time()
    platoon.run(steps)
    elapsed, cpu = time.perf_counter() - started, time.process_time() - cpu_started
    return {"seconds": elapsed, "cpu_seconds": cpu, "started": started, "final": platoon.finals()}


def measure_step(engine: str, n: int, steps: int, coupling: str = "extrapolate",
                 fmu_dir: Path = DEFAULT_OUT) -> dict[str, Any]:
    """Time ``steps`` steps of the N-vehicle platoon with ``engine``: µs per FMU-step, wall and CPU.

    Also reports how many garbage collections Python ran in the timed loop, and the RSS at the end.
    """
    from .libcosim import run_libcosim

    runners: dict[str, Callable[[], dict[str, Any]]] = {
        "native": lambda: run_native(n, steps, "off", coupling, fmu_dir),
        "native-buffer": lambda: run_native(n, steps, "buffer", coupling, fmu_dir),
        "native-traced": lambda: run_native(n, steps, "traced", coupling, fmu_dir),
        "native-offload": lambda: run_native(n, steps, "offload", coupling, fmu_dir),
        "python": lambda: run_python(n, steps, coupling, fmu_dir),
        "fmpy-bare": lambda: run_fmpy_bare(n, steps, coupling, fmu_dir),
        "libcosim": lambda: run_libcosim(n, steps, False, coupling, fmu_dir),
        "libcosim-0threads": lambda: run_libcosim(n, steps, True, coupling, fmu_dir),
        "libcosim-0threads-lastvalue": lambda: run_libcosim(n, steps, True, coupling, fmu_dir, observer="last-value"),
        "slaves": lambda: run_slaves(n, steps, coupling, fmu_dir),
    }
    gc.callbacks.append(_note_collection)
    try:
        result = runners[engine]()
    finally:
        gc.callbacks.remove(_note_collection)
    started = result.pop("started")
    timed_collections = sum(started <= moment <= started + result["seconds"] for moment in _collected_at)
    timed = result.setdefault("timed_steps", steps)
    result.update(engine=engine, n=n, steps=steps, coupling=coupling,
                  us_per_fmu_step=result["seconds"] / (timed * (n + 1)) * 1e6,
                  cpu_us_per_fmu_step=result["cpu_seconds"] / (timed * (n + 1)) * 1e6,
                  gc_collections=timed_collections, rss_kib=rss_kib())
    return result
