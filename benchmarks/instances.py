"""Suite ``instances``: instantiation time and RSS per vehicle instance (what a big
platoon costs before its first step).

In a fresh interpreter, with the FMUs unpacked, the child collects garbage and reads VmRSS, then
creates the components and the master of the N-vehicle platoon (1 target + N vehicles) and
initializes it (fmi2Instantiate, fmi2SetupExperiment, parameters, initialization mode, settle sweeps,
exit), collects garbage and reads VmRSS again. Engines:

* ``native``: NativeComponent + NativeMaster (instances created by the C core);
* ``fmpy``: FmuComponent + Master, the Python engine on FMPy's FMU2Slave.

Wirings: ``instances`` leaves the components unconnected, so the settle sweeps stop after the first
sweep and the cost is the instances' own; ``platoon`` wires them as the paper's Fig. 2, where the
settle sweeps propagate values along the chain (up to N + 2 sweeps, each touching every component,
so this part grows as N²). The per-vehicle cost is the slope of a least-squares line through the
medians over N; the intercept is what any run pays once (loading the binaries, importing the model).
"""

from __future__ import annotations

import gc
import statistics
import time
from pathlib import Path
from typing import Any, Sequence

from fmus.builders import DEFAULT_OUT

from .common import BenchUsageError, Progress, interleaved, markdown_table, rss_kib, run_child, slope
from .platoon import fmu_files, scenario_for, unpacked_fmus

ENGINES = ("native", "fmpy")
WIRINGS = ("instances", "platoon")
DEFAULT_N = (4, 16, 64, 256)
LABELS = {"native": "native engine (C core)", "fmpy": "Python engine (FMPy FMU2Slave)"}


def measure_instances(engine: str, n: int, wired: bool, fmu_dir: Path) -> dict[str, Any]:
    """Time and RSS growth of creating and initializing the N-vehicle platoon's instances (child side)."""
    scenario = scenario_for(n, 1)
    fmus = unpacked_fmus(fmu_dir)
    connections = scenario.connections if wired else []
    gc.collect()
    rss_before = rss_kib()
    started = time.perf_counter()
    if engine == "native":
        from orchestrator.execution.native import NativeComponent, NativeMaster

        master: Any = NativeMaster([NativeComponent(s.name, fmus[s.fmu], s.parameters) for s in scenario.components],
                                   connections, scenario.schedules, "jacobi")
    elif engine == "fmpy":
        from orchestrator.components.fmu import FmuComponent
        from orchestrator.execution.python_master import Master

        master = Master([FmuComponent(s.name, fmus[s.fmu], s.parameters) for s in scenario.components],
                        connections, scenario.schedules, "jacobi")
    else:
        raise ValueError(f"unknown engine {engine!r}")
    constructed = time.perf_counter()
    master.initialize(0.0)
    initialized = time.perf_counter()
    gc.collect()
    rss_after = rss_kib()
    master.close()
    return {"engine": engine, "n": n, "wired": wired, "instances": n + 1,
            "construct_s": constructed - started, "initialize_s": initialized - constructed,
            "total_s": initialized - started, "rss_before_kib": rss_before, "rss_after_kib": rss_after,
            "rss_growth_kib": rss_after - rss_before}


def run(engines: Sequence[str] = ENGINES, ns: Sequence[int] = DEFAULT_N, rounds: int = 3,
        wirings: Sequence[str] = WIRINGS, fmu_dir: Path = DEFAULT_OUT,
        progress: Progress | None = None) -> dict[str, Any]:
    unknown = [e for e in engines if e not in ENGINES]
    if unknown:
        raise BenchUsageError(f"unknown engine(s) {', '.join(unknown)} for instances; expected some of {', '.join(ENGINES)}")
    if "native" in engines:
        from orchestrator.execution.native import available

        if not available():
            raise BenchUsageError("the native engine needs the compiled core (reinstall with a C compiler: pip install -e .)")
    started = time.perf_counter()
    fmu_files(fmu_dir)
    folder = str(Path(fmu_dir).resolve())

    def measure(n: int, variant: tuple[str, str]) -> dict[str, Any]:
        wiring, engine = variant
        result = run_child({"kind": "instances", "engine": engine, "n": n, "wired": wiring == "platoon",
                            "fmu_dir": folder})
        result["wiring"] = wiring
        return result

    def describe(result: dict[str, Any]) -> str:
        return (f"N={result['n']:<4} {result['engine']:<7} {result['wiring']:<10}{result['total_s'] * 1e3:9.1f} ms  "
                f"+{result['rss_growth_kib'] / 1024:7.1f} MiB")

    samples = interleaved(rounds, ns, [(w, e) for w in wirings for e in engines], measure, describe, progress)
    medians: dict[str, dict[str, dict[int, dict[str, float]]]] = {}
    per_vehicle: dict[str, dict[str, dict[str, float]]] = {}
    for wiring in wirings:
        for engine in engines:
            by_n = {}
            for n in ns:
                mine = [s for s in samples if s["engine"] == engine and s["n"] == n and s["wiring"] == wiring]
                by_n[n] = {key: statistics.median(s[key] for s in mine)
                           for key in ("construct_s", "initialize_s", "total_s", "rss_growth_kib")}
            medians.setdefault(wiring, {})[engine] = by_n
            time_intercept, time_slope = slope(list(ns), [by_n[n]["total_s"] for n in ns])
            rss_intercept, rss_slope = slope(list(ns), [by_n[n]["rss_growth_kib"] for n in ns])
            per_vehicle.setdefault(wiring, {})[engine] = {
                "ms_per_vehicle": time_slope * 1e3, "ms_intercept": time_intercept * 1e3,
                "kib_per_vehicle": rss_slope, "kib_intercept": rss_intercept}
    return {"n": list(ns), "rounds": rounds, "engines": list(engines), "wirings": list(wirings),
            "medians": medians, "per_vehicle_slope": per_vehicle, "samples": samples,
            "seconds": time.perf_counter() - started}


def markdown(result: dict[str, Any]) -> str:
    ns = result["n"]
    rows = []
    for wiring in result["wirings"]:
        for engine in result["engines"]:
            by_n = result["medians"][wiring][engine]
            fit = result["per_vehicle_slope"][wiring][engine]
            rows.append([LABELS[engine], wiring,
                         *(f"{by_n[n]['total_s'] * 1e3:.0f} ms / {by_n[n]['rss_growth_kib'] / 1024:.1f} MiB" for n in ns),
                         f"**{fit['ms_per_vehicle']:.2f} ms**", f"**{fit['kib_per_vehicle']:.0f} KiB**"])
    return (f"create + initialize 1 target + N vehicles: wall time / RSS growth, median of {result['rounds']} "
            f"interleaved rounds; per vehicle = least-squares slope over N\n\n"
            + markdown_table(["engine", "wiring", *(f"N={n}" for n in ns), "time per vehicle", "RSS per vehicle"], rows))
