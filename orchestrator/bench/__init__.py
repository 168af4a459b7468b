"""Every benchmark of the project, in one place: inside the installed package, since
``platoon bench`` is an installed command. Run them from the repository: configs, the FMUs
(``build/fmus``) and the results (``runs/bench/``) are found relative to the current folder.

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
* ``cores LABEL=PATH LABEL=PATH``: the native engine with two or more builds of _core.c (``flatness.py``).

``python -m orchestrator.bench.<name>`` (each module's docstring has its options):

* ``trace_overhead``: what tracing every step costs, untraced / in process / second process;
* ``trace_encoder``: CPU per component and row of the Python and the C trace encoder, zstd levels;
* ``trace_memory``: RSS and wall time of the 100-vehicle, 1-hour traced run, sampled from inside;
* ``paper_scenarios``: every paper scenario with both laws: summaries, peaks, wall times (docs/reproduction.md);
* ``coupling_accuracy [--master gauss-seidel]``: the coupling error table of docs/coupling.md;
* ``fmu_step_cost``: one doStep of each FMU under FMPy, against its stepper called directly;
* ``equilibrium_growth TRACE``: how far a platoon started on its equilibrium strays from it (docs/model.md).

Every timed measurement runs in a fresh interpreter (``orchestrator.bench.child``), so libraries,
caches and the heap never carry over from one measurement to the next and a pythonfmu or libcosim
teardown cannot disturb the next one. Repetitions are interleaved (every variant once per round, the
order rotated each round) and results are medians, so that drift of this shared machine hits every
variant alike. ``common.py`` holds what they share (child processes, interleaving, the result file);
``platoon.py``, ``engines.py``, ``floor.py`` and ``libcosim.py`` the platoon and the engines measured.
"""

# The engines the per-FMU-step suites know (described in engines.py); here so that the CLI can list
# them without importing FMPy.
ENGINES = ("native", "native-buffer", "native-traced", "native-offload", "python", "fmpy-bare", "libcosim",
           "libcosim-0threads", "libcosim-0threads-lastvalue", "slaves")
