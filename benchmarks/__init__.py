"""Every benchmark of the project, in one place: beside the package, not in it (as libcosim and FMPy keep
theirs). The installed wheel holds none of them: they need the repository anyway (configs, the FMUs in
``build/fmus``, the results under ``runs/bench/``, all relative to the current folder), and carry harnesses
(libcosimpy, perf, callgrind) no user of the tool needs. Run them from a checkout: ``platoon bench ...``
finds this folder there (orchestrator/cli/bench.py), or ``python -m benchmarks.<name>``.

``platoon bench <suite>`` (orchestrator/cli/bench.py; JSON under ``runs/bench/<suite>-<time>.json``):

* ``steps``: µs per FMU-step of our engines against the bare FMPy loop, libcosim and the floor, by N (``steps.py``);
* ``coupling``: the same cost with coupling "hold" against "extrapolate" (``coupling.py``);
* ``scenarios``: whole-run wall times of the paper's scenarios, start-up included (``scenarios.py``);
* ``instances``: instantiation time and RSS per vehicle instance (``instances.py``);
* ``profile``: where the native engine's time goes, in one process, with ``perf`` (``profile.py``);
* ``flatness``: why the cost per FMU-step grows with N: stepping order, idle instances (``flatness.py``);
* ``callgrind``: instructions and simulated cache misses per FMU-step, the master's own apart (``flatness.py``);
* ``hil``: Zenoh round trip and step jitter of live runs on loopback (``hil.py``);
* ``sweep``: wall time of a sweep with 1, 2, ... local workers and on Dask; the speed-up (``sweep.py``);
* ``readback``: each trace reader (load, report, stability, stability-map) against the run that wrote the
  trace, whole processes in one sitting; load's peak memory against its arrays (``readback.py``);
* ``remote``: a macro step of N remote vehicles (``platoon serve``) in lockstep, one by one, local, and the
  Zenoh round trip, in one sitting (``remote.py``);
* ``startup``: each command's time to first output, and a sweep's cost per run against the run's own work
  (``startup.py``);
* ``cores LABEL=PATH LABEL=PATH``: the native engine with two or more builds of _core.c (``flatness.py``).

``python -m benchmarks.<name>`` (each module's docstring has its options):

* ``trace_overhead``: what tracing every step costs, untraced / in process / second process;
* ``trace_encoder``: CPU per component and row of the Python and the C trace encoder, zstd levels;
* ``trace_memory``: RSS and wall time of the 100-vehicle, 1-hour traced run, sampled from inside;
* ``paper_scenarios``: every paper scenario with both laws: summaries, peaks, wall times (docs/reproduction.md);
* ``coupling_accuracy [--master gauss-seidel]``: the coupling error table of docs/coupling.md;
* ``fmu_step_cost``: one doStep of each FMU under FMPy, against its stepper called directly;
* ``equilibrium_growth TRACE``: how far a platoon started on its equilibrium strays from it (docs/model.md).

Every timed measurement runs in a fresh interpreter (``benchmarks.child``), so libraries,
caches and the heap never carry over from one measurement to the next and a pythonfmu or libcosim
teardown cannot disturb the next one. Repetitions are interleaved (every variant once per round, the
order rotated each round) and results are medians, so that drift of this shared machine hits every
variant alike. ``common.py`` holds what they share (child processes, interleaving, the result file);
``platoon.py``, ``engines.py``, ``floor.py`` and ``libcosim.py`` the platoon and the engines measured.
"""

import os
from pathlib import Path

# Measurements run in fresh interpreters (``python -m benchmarks.child`` ...): they find this folder through
# PYTHONPATH wherever they start, as this process found it.
CHECKOUT = Path(__file__).resolve().parent.parent
if str(CHECKOUT) not in os.environ.get("PYTHONPATH", "").split(os.pathsep):
    os.environ["PYTHONPATH"] = os.pathsep.join(filter(None, (str(CHECKOUT), os.environ.get("PYTHONPATH"))))
