"""Benchmarks of issue 10, importable so that ``platoon bench`` and ``benchmarks/*.py`` share one copy.

Every measurement runs in a fresh interpreter (``orchestrator.bench.child``), so libraries, caches and
the heap never carry over from one measurement to the next and a pythonfmu or libcosim teardown
cannot disturb the next one. Repetitions are interleaved (every variant once per round, the order
rotated each round) and results are medians, so that drift of this shared machine hits every
variant alike. Suites:

* ``steps``: microseconds per FMU-step of our engines and of the peers (``steps.py``);
* ``coupling``: the same cost with coupling "hold" against "extrapolate" (``coupling.py``);
* ``scenarios``: whole-run wall times of the paper's scenarios, start-up included (``scenarios.py``);
* ``instances``: instantiation time and RSS per vehicle instance (``instances.py``);
* ``profile``: where the native engine's time goes, in one process (``profile.py``).

Each suite returns a JSON-ready dict (samples, medians, ratios, versions, machine) and renders it as
Markdown tables; ``common.write_result`` stores it under ``runs/bench/``.
"""

# The engines the per-FMU-step suites know (described in engines.py); here so that the CLI can list
# them without importing FMPy.
ENGINES = ("native", "native-buffer", "native-traced", "native-offload", "python", "fmpy-bare", "libcosim",
           "libcosim-0threads", "slaves")
