"""libcosim (libcosimpy, the C++ Open Simulation Platform master) on our own FMUs and wiring.

Two set-ups, libcosim as it is usually run and libcosim stepping as ours does: ``CosimExecution.from_step_size`` with libcosim's default worker
threads, and an SSP package written at run time by ``orchestrator.interop.ssp.write_ssp`` (the exporter of
``platoon export-ssp``) with ``<osp:FixedStepAlgorithm numWorkerThreads="0">`` (every FMU stepped on
the calling thread, as ours).
"""

from __future__ import annotations

import tempfile
import time
from pathlib import Path
from typing import Any

from fmus.builders import DEFAULT_OUT

from orchestrator.interop.ssp import write_ssp
from .common import BenchError
from .platoon import STEP, fmu_files, scenario_for

NANOSECONDS = 1_000_000_000


def _check(ok: object, what: str) -> None:
    if not ok:
        raise BenchError(f"libcosim: {what} failed")


def run_libcosim(n: int, steps: int, from_ssp: bool, coupling: str = "extrapolate",
                 fmu_dir: Path = DEFAULT_OUT, observer: str = "none") -> dict[str, Any]:
    """libcosim (libcosimpy) on our platoon: default worker threads, or from an SSP file with 0 threads.

    ``observer`` during the timed steps: "none", as our engines with tracing off (the fair baseline),
    or "last-value", libcosim's observer that reads every variable of every slave after each step
    (what this benchmark first attached: it made libcosim 1.27-1.32x slower, not a fair reference). Either
    way a last-value observer is added for the last, untimed step, to read the final positions.
    """
    if observer not in ("none", "last-value"):
        raise BenchError(f"unknown libcosim observer {observer!r}")
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
        package = Path(tempfile.mkdtemp(prefix="bench-ssp-")) / "platoon.ssp"
        execution = CosimExecution.from_ssp_file(str(write_ssp(package, scenario, paths, worker_threads=0)))
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
    if observer == "last-value":
        _check(execution.add_observer(last), "add the observer")
    _check(execution.step(1), "first step")  # libcosim initializes on its first step: time the other steps - 2
    started, cpu_started = time.perf_counter(), time.process_time()
    _check(execution.step(steps - 2), "stepping")
    elapsed, cpu = time.perf_counter() - started, time.process_time() - cpu_started
    if observer == "none":
        _check(execution.add_observer(last), "add the observer")
    _check(execution.step(1), "the last step")  # untimed: the observer reads the final positions
    _check(execution.status().current_time == steps * step_ns, "the end time")
    final = {name: last.last_real_values(i, [variables[name]["x"][0], variables[name]["y"][0]])
             for name, i in index.items()}
    return {"seconds": elapsed, "cpu_seconds": cpu, "started": started, "final": {k: list(v) for k, v in final.items()},
            "timed_steps": steps - 2}
