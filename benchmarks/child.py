"""One measurement in a fresh interpreter: ``python -m benchmarks.child '<task as JSON>'``.

Prints one ``RESULT <json>`` line and leaves with ``os._exit`` (pythonfmu leaves objects in the
interpreter whose teardown can corrupt the heap, see orchestrator/cli/app.py: main). Nothing is imported
at module level beyond the standard library, so that a whole-run measurement's start-up is the run's
own (``wholerun`` is timed from outside, interpreter start included).
"""

from __future__ import annotations

import json
import os
import sys
import traceback
from pathlib import Path
from typing import Any


def use_core(library: str) -> None:
    """Make ``orchestrator.execution.native._core`` the extension built at ``library`` (another build of
    _core.c), before anything imports the native engine: A/B measurements of two cores."""
    import importlib.machinery
    import importlib.util

    name = "orchestrator.execution.native._core"
    spec = importlib.util.spec_from_file_location(name, library,
                                                  loader=importlib.machinery.ExtensionFileLoader(name, library))
    if spec is None or spec.loader is None:
        raise ImportError(f"cannot load {library}")
    module = importlib.util.module_from_spec(spec)
    sys.modules[name] = module
    spec.loader.exec_module(module)


def perform(task: dict[str, Any]) -> dict[str, Any]:
    kind = task["kind"]
    if task.get("core"):
        use_core(task["core"])
    fmu_dir = Path(task["fmu_dir"])
    if kind == "step":
        # One OpenBLAS thread, as in `platoon run`: otherwise numpy's idle BLAS threads spin on the other
        # core and are counted in the process CPU time the step measurement reports beside wall time
        # (seen: 1.0 µs of CPU per 0.5 µs of wall for the native FMUs).
        from orchestrator.support.startup import single_threaded_blas

        single_threaded_blas()
        from .engines import measure_step

        return measure_step(task["engine"], task["n"], task["steps"], task.get("coupling", "extrapolate"), fmu_dir)
    if kind == "instances":
        from .instances import measure_instances

        return measure_instances(task["engine"], task["n"], task["wired"], fmu_dir)
    if kind == "wholerun":
        from .scenarios import whole_run

        return whole_run(Path(task["config"]), task["engine"], task.get("out"), task.get("overrides", []), fmu_dir)
    if kind == "profile":
        from .profile import profile

        return profile(task["n"], task["steps"], task["rounds"], fmu_dir)
    if kind == "flatness":
        from .flatness import measure_orders

        return measure_orders(task["n"], task["steps"], task["rounds"], task["idle"], fmu_dir)
    if kind == "trace-overhead":
        from .trace_overhead import traced_run

        return traced_run(Path(task["config"]), task["variant"], task["engine"], task["n"], task["steps"],
                          Path(task["out_dir"]), fmu_dir)
    if kind == "callgrind":
        from .flatness import callgrind_target

        return callgrind_target(task["n"], task["steps"], task["client"], fmu_dir, task.get("engine", "native"))
    if kind == "sweep-bookkeeping":
        from .sweep_bookkeeping import measure

        return measure(task["points"], task.get("first_run_only", False))
    raise ValueError(f"unknown task kind {kind!r}")


def main() -> None:
    from orchestrator.support.internal_entry import check_arguments

    check_arguments(sys.argv[1:], "python -m benchmarks.child '<task as JSON>'", __doc__, count=1)
    code = 0
    try:
        result = perform(json.loads(sys.argv[1]))
        sys.stdout.write("RESULT " + json.dumps(result) + "\n")
    except BaseException:  # report, then leave without interpreter teardown all the same
        traceback.print_exc()
        code = 1
    sys.stdout.flush()
    sys.stderr.flush()
    os._exit(code)


if __name__ == "__main__":
    main()
