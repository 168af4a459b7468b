"""Suite ``flatness``: why the cost per FMU-step grows with N, with evidence (a
platoon twice as long should cost twice as much per step, not more).

Three experiments, each N in a fresh interpreter:

* **orders** (in process, interleaved): the floor (slave classes called directly, ``floor.DirectLoop``)
  stepping the whole platoon in Master's order, phases (set every input, step every component, get
  every output), against per-component order (all inputs transferred first, then per component
  set, step, get back to back: same calls per component, same results). If the growth is cache
  misses from touching every instance between two calls on the same instance, the per-component
  order removes most of it.
* **idle**: the N-vehicle platoon is created and initialized, but only its first 5 components
  (target + 4 vehicles) are stepped. If the cost per FMU-step of those 5 stays at the N = 4 level,
  the growth comes from the instances touched per step (working set), not from the number of live
  objects (allocator, garbage collector, interpreter caches).
* **objects**: Python objects, allocated blocks and RSS per instance, to size the working set.

``callgrind`` (valgrind) counts instructions and simulated cache misses of an engine's stepping only
(instrumentation switched on around the stepping by a client request), per FMU-step: flat
instruction counts with growing misses point at memory, growing instruction counts at work. It also
splits every count into inside the FMUs' fmi2 calls and the master's own.

``cores`` times the native engine with two or more builds of orchestrator/execution/native/_core.c (copy the
built ``orchestrator/execution/native/_core.*.so`` aside before rebuilding), interleaved in fresh interpreters;
``callgrind`` takes such builds too.

Entry points: ``platoon bench flatness`` (orders, idle, objects; ``--callgrind`` adds the callgrind
series of the native and Python engines), ``platoon bench callgrind`` (callgrind alone: engines,
cache models and core builds to choose) and ``platoon bench cores LABEL=PATH LABEL=PATH``.
"""

from __future__ import annotations

import gc
import json
import os
import re
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any, Sequence

from fmus.builders import DEFAULT_OUT

from .common import BenchUsageError, Progress, interleaved, markdown_table, rss_kib, run_child
from .floor import ORDERS, DirectLoop, SlavePlatoon
from .platoon import fmu_files

SUBSET = 5  # components stepped in the idle experiment: the N = 4 platoon's size
L2 = "524288,8,64"  # this machine's L2 per core (512 KiB, 8-way, 64-byte lines) as callgrind's last level
LAST_LEVELS = {"l2": L2, "detected": None}  # callgrind's last level by name: this L2, or valgrind's detected L3
CALLGRIND_ENGINES = ("native", "python", "fmpy-bare")
DEFAULT_N = (4, 16, 64, 256)


def core_builds(items: Sequence[str]) -> dict[str, str]:
    """``LABEL=PATH`` items, each a built _core extension, as {label: absolute path}."""
    cores = {}
    for item in items:
        label, _, path = item.partition("=")
        if not label or not path or not Path(path).is_file():
            raise BenchUsageError(f"expected LABEL=PATH to a built _core .so, got {item!r}")
        cores[label] = str(Path(path).resolve())
    return cores


def _subset_loop(platoon: SlavePlatoon, m: int) -> DirectLoop:
    """The first ``m`` components of ``platoon``; inputs from components outside keep their values."""
    routes = [[(i, source, o) for i, source, o in platoon.routes[c] if source < m] for c in range(m)]
    return DirectLoop(platoon.setters[:m], platoon.steppers[:m], platoon.getters[:m], platoon.in_refs[:m],
                      platoon.out_refs[:m], platoon.inputs[:m], routes, platoon.names[:m])


def measure_orders(n: int, steps: int, rounds: int, idle: bool, fmu_dir: Path) -> dict[str, Any]:
    """Child side: µs per FMU-step by order (interleaved in this process), or of the idle subset."""
    SlavePlatoon(1, 1, fmu_dir=fmu_dir)  # modules imported, files unpacked: not counted per instance
    gc.collect()
    objects_before, blocks_before, rss_before = len(gc.get_objects()), sys.getallocatedblocks(), rss_kib()
    platoon = SlavePlatoon(n, steps * (2 * rounds + 1), fmu_dir=fmu_dir)
    gc.collect()
    sizes = {"objects_per_instance": (len(gc.get_objects()) - objects_before) / (n + 1),
             "blocks_per_instance": (sys.getallocatedblocks() - blocks_before) / (n + 1),
             "rss_kib_per_instance": (rss_kib() - rss_before) / (n + 1)}
    loop = _subset_loop(platoon, SUBSET) if idle else platoon
    stepped = SUBSET if idle else n + 1
    loop.run(steps // 4 or 1)  # warm-up: caches, specialised bytecode
    samples: dict[str, list[float]] = {order: [] for order in (("phases",) if idle else ORDERS)}
    for round_ in range(rounds):
        orders = list(samples)
        for order in orders[round_ % len(orders):] + orders[:round_ % len(orders)]:
            started = time.perf_counter()
            loop.run(steps, order)
            samples[order].append((time.perf_counter() - started) / (steps * stepped) * 1e6)
    by_kind: dict[str, float] = {}
    if not idle:  # µs per call triple (set, step, get) of a target and of a vehicle, in the platoon
        loop.run_split(steps)
        kinds = [spec.fmu for spec in platoon.scenario.components]
        for kind in sorted(set(kinds)):
            spent = [s for s, k in zip(platoon.spent_by_component, kinds) if k == kind]
            by_kind[kind] = sum(spent) / (len(spent) * steps) * 1e6
    return {"n": n, "idle": idle, "stepped": stepped, "steps": steps, "rounds": rounds, **sizes,
            "us": {order: statistics.median(values) for order, values in samples.items()}, "samples": samples,
            "us_by_kind": by_kind}


def run(ns: Sequence[int] = DEFAULT_N, steps: int = 150, rounds: int = 5, repeats: int = 3,
        fmu_dir: Path = DEFAULT_OUT, progress: Progress | None = None) -> dict[str, Any]:
    """Each N ``repeats`` times (fresh interpreter each, N order rotated), orders and idle subset."""
    fmu_files(fmu_dir)
    folder = str(Path(fmu_dir).resolve())
    started = time.perf_counter()
    results: list[dict[str, Any]] = []
    variants = [(n, idle) for n in ns for idle in (False, True) if not (idle and n + 1 <= SUBSET)]
    total = repeats * len(variants)
    for repeat in range(repeats):
        shift = repeat % len(variants)
        for n, idle in variants[shift:] + variants[:shift]:
            result = run_child({"kind": "flatness", "n": n, "steps": steps, "rounds": rounds, "idle": idle,
                                "fmu_dir": folder})
            result["repeat"] = repeat
            results.append(result)
            if progress is not None:
                progress(len(results), total, f"repeat {repeat + 1}/{repeats}  N={n:<4} "
                         + ("idle: 5 of N stepped " if idle else "") + ", ".join(
                             f"{order} {value:.2f}" for order, value in result["us"].items()) + " µs/FMU-step")
    medians: dict[str, dict[int, float]] = {}
    for key, order, idle in (("phases", "phases", False), ("per-component", "per-component", False),
                             ("idle", "phases", True)):
        for n in ns:
            values = [r["us"][order] for r in results if r["n"] == n and r["idle"] == idle]
            if values:
                medians.setdefault(key, {})[n] = statistics.median(values)
    sizes = {n: {k: statistics.median(r[k] for r in results if r["n"] == n and not r["idle"])
                 for k in ("objects_per_instance", "blocks_per_instance", "rss_kib_per_instance")} for n in ns}
    by_kind = {n: {kind: statistics.median(r["us_by_kind"][kind] for r in results if r["n"] == n and not r["idle"])
                   for kind in ("VirtualTarget", "Vehicle")} for n in ns}
    return {"n": list(ns), "steps": steps, "rounds": rounds, "repeats": repeats, "medians": medians, "sizes": sizes,
            "us_by_kind": by_kind, "results": results, "seconds": time.perf_counter() - started}


def markdown(result: dict[str, Any]) -> str:
    ns, medians = result["n"], result["medians"]
    labels = {"phases": "floor, Master's order (set all, step all, get all)",
              "per-component": "floor, per-component order (set, step, get back to back)",
              "idle": f"floor, only {SUBSET} of the N + 1 components stepped"}
    rows = [[labels[key], *(f"{by_n[n]:.1f}" if n in by_n else "-" for n in ns),
             f"{by_n[ns[-1]] / by_n[ns[0]]:.2f}" if ns[0] in by_n and ns[-1] in by_n else "-"]
            for key, by_n in medians.items()]
    if "phases" in medians and "per-component" in medians:
        rows.append(["per-component / phases", *(f"{medians['per-component'][n] / medians['phases'][n]:.2f}" for n in ns), ""])
    by_kind = result["us_by_kind"]
    for kind in ("VirtualTarget", "Vehicle"):
        rows.append([f"floor, one {kind}: set + step + get, each call timed", *(f"{by_kind[n][kind]:.1f}" for n in ns),
                     f"{by_kind[ns[-1]][kind] / by_kind[ns[0]][kind]:.2f}"])
    sizes = result["sizes"]
    size_rows = [[key.replace("_", " "), *(f"{sizes[n][key]:.0f}" for n in ns)]
                 for key in ("objects_per_instance", "blocks_per_instance", "rss_kib_per_instance")]
    return (f"µs per FMU-step, median over {result['repeats']} processes of the median of {result['rounds']} "
            f"interleaved samples of {result['steps']} steps\n\n"
            + markdown_table(["loop", *(f"N={n}" for n in ns), f"N={ns[-1]} / N={ns[0]}"], rows)
            + "\n\nsize of one instance (slave + its Python objects)\n\n"
            + markdown_table(["", *(f"N={n}" for n in ns)], size_rows))


# --- callgrind: instructions and simulated cache misses of the native core's stepping ---------------

_CLIENT_REQUESTS = r"""
#include <valgrind/callgrind.h>
void instrumentation_on(void) { CALLGRIND_START_INSTRUMENTATION; }
void instrumentation_off(void) { CALLGRIND_STOP_INSTRUMENTATION; }
"""
_EVENTS = ("Ir", "Dr", "Dw", "I1mr", "D1mr", "D1mw", "ILmr", "DLmr", "DLmw")


def _client_library(folder: Path) -> Path:
    """A tiny shared library whose two functions are callgrind's start/stop instrumentation requests."""
    source, library = folder / "client.c", folder / "client.so"
    source.write_text(_CLIENT_REQUESTS)
    subprocess.run(["cc", "-O0", "-shared", "-fPIC", "-o", str(library), str(source)], check=True)
    return library


def callgrind_target(n: int, steps: int, client: str, fmu_dir: Path, engine: str = "native") -> dict[str, Any]:
    """Child side, under valgrind: initialize the platoon and step it ``steps`` times uninstrumented
    (warm-up), then instrument only the next ``steps`` steps: ``Core.run`` (native), ``Master.step``
    (python) or the bare FMPy loop (fmpy-bare), as the benchmark's timed loops run them."""
    import ctypes

    from .platoon import STEP, scenario_for, unpacked_fmus

    if engine in ("native", "python"):
        scenario = scenario_for(n, 2 * steps)
        fmus = unpacked_fmus(fmu_dir)
    if engine == "native":
        from orchestrator.execution.native import NativeComponent, NativeMaster

        master: Any = NativeMaster([NativeComponent(s.name, fmus[s.fmu], s.parameters) for s in scenario.components],
                                   scenario.connections)
        master.initialize(0.0)

        def go(first: int, stop: int) -> None:
            master._core.run(0.0, STEP, first, stop)
        finish = master.close
    elif engine == "python":
        from orchestrator.components.fmu import FmuComponent
        from orchestrator.execution.python_master import Master

        from .engines import step_python_master

        master = Master([FmuComponent(s.name, fmus[s.fmu], s.parameters) for s in scenario.components],
                        scenario.connections)
        master.initialize(0.0)

        def go(first: int, stop: int) -> None:
            step_python_master(master, first, stop)
        finish = master.close
    elif engine == "fmpy-bare":
        from .engines import fmpy_bare_platoon, free_fmpy_slaves

        loop, slaves, _ = fmpy_bare_platoon(n, 2 * steps, "extrapolate", fmu_dir)

        def go(first: int, stop: int) -> None:
            loop.run(stop - first)  # the loop keeps its own step count

        def finish() -> None:
            free_fmpy_slaves(slaves)
    else:
        raise ValueError(f"callgrind: unknown engine {engine!r} ({', '.join(CALLGRIND_ENGINES)})")
    go(0, steps)  # warm-up, uninstrumented
    requests = ctypes.CDLL(client)
    requests.instrumentation_on()
    go(steps, 2 * steps)
    requests.instrumentation_off()
    finish()
    return {"n": n, "steps": steps, "engine": engine}


# pythonfmu's slave-instance methods, not the std::function helpers inside them (callgrind_annotate
# lists those with the method's name in theirs): everything an fmi2SetReal, fmi2DoStep or fmi2GetReal
# does inside the FMU, the Python slave included, except the few instructions of the exported fmi2
# function that forwards to them. What is left of the instrumented total is the master's own work and
# the cost of calling into the FMU.
_INSIDE_FMU = re.compile(r"[^\s:]*:PySlaveInstance::(SetReal|Step|GetReal)\(")
# One callgrind_annotate line: a column per event ("1,234 (5.6%)", or "." for none), then the function.
_ANNOTATION_LINE = re.compile(r"\s*(?P<columns>(?:(?:[\d,]+ \(\s*[\d.]+%\)|\.)\s+)+)(?P<function>\S.*)")
_ANNOTATION_COLUMN = re.compile(r"([\d,]+) \(\s*[\d.]+%\)|\.")


def inside_fmu_counts(profile: Path, events: Sequence[str]) -> dict[str, int]:
    """Each event's count inside the FMUs' fmi2SetReal / fmi2DoStep / fmi2GetReal, from
    callgrind_annotate's inclusive counts of ``profile``."""
    done = subprocess.run(["callgrind_annotate", "--inclusive=yes", f"--show={','.join(events)}", "--threshold=100",
                           str(profile)], capture_output=True, text=True, check=True)
    return inside_fmu_from_annotation(done.stdout, events)


def inside_fmu_from_annotation(annotation: str, events: Sequence[str]) -> dict[str, int]:
    """The sums of the inclusive counts of pythonfmu's SetReal, Step and GetReal (every FMU binary's)
    in a ``callgrind_annotate --inclusive=yes --show=<events>`` listing."""
    totals = dict.fromkeys(events, 0)
    for line in annotation.splitlines():
        entry = _ANNOTATION_LINE.match(line)
        if entry and _INSIDE_FMU.match(entry["function"]):
            columns = [int(count.replace(",", "")) if count else 0
                       for count in _ANNOTATION_COLUMN.findall(entry["columns"])]
            if len(columns) != len(events):
                raise ValueError(f"callgrind_annotate line with {len(columns)} columns, expected {len(events)}: {line!r}")
            for event, count in zip(events, columns):
                totals[event] += count
    return totals


def callgrind(n: int, steps: int, last_level: str | None, core: str | None = None,
              fmu_dir: Path = DEFAULT_OUT, engine: str = "native") -> dict[str, Any]:
    """Per FMU-step: instructions (Ir), data reads/writes and simulated misses of ``engine`` stepping,
    and each count split into inside the FMUs (``<event>_fmu``) and the master's own (``<event>_master``:
    its loop, transfers and the FMI calls' mechanics, ctypes and libffi for the Python engine).

    ``last_level``: valgrind's ``--LL=size,assoc,line`` (e.g. this machine's L2, 524288,8,64), or None
    for valgrind's own choice (the L3 as detected). ``core``: another build of _core.c to measure."""
    if shutil.which("valgrind") is None:
        raise BenchUsageError("callgrind needs valgrind (apt-get install valgrind)")
    with tempfile.TemporaryDirectory(prefix="bench-callgrind-") as scratch:
        folder = Path(scratch)
        client = _client_library(folder)
        out = folder / "callgrind.out"
        task = {"kind": "callgrind", "n": n, "steps": steps, "client": str(client), "core": core, "engine": engine,
                "fmu_dir": str(Path(fmu_dir).resolve())}
        command = ["valgrind", "--tool=callgrind", "--instr-atstart=no", "--cache-sim=yes",
                   f"--callgrind-out-file={out}", *([f"--LL={last_level}"] if last_level else []),
                   sys.executable, "-m", "benchmarks.child", json.dumps(task)]
        done = subprocess.run(command, capture_output=True, text=True, env={**os.environ, "PYTHONMALLOC": "pymalloc"})
        if done.returncode != 0 or not out.exists():
            raise RuntimeError(f"callgrind N={n} failed:\n{done.stdout[-2000:]}\n{done.stderr[-3000:]}")
        events, totals = None, None
        for line in out.read_text().splitlines():
            if line.startswith("events:"):
                events = line.split()[1:]
            elif line.startswith("totals:") or line.startswith("summary:"):
                totals = [int(v) for v in line.split()[1:]]
        if events is None or totals is None:
            raise RuntimeError(f"no totals in {out}")
        inside = inside_fmu_counts(out, events)
        notes = [line for line in done.stderr.splitlines() if "warning" in line.lower()][:5]  # e.g. the LL choice
    fmu_steps = steps * (n + 1)
    per_step = {event: value / fmu_steps for event, value in zip(events, totals)}
    for event in events:
        per_step[f"{event}_fmu"] = inside[event] / fmu_steps
        per_step[f"{event}_master"] = per_step[event] - per_step[f"{event}_fmu"]
    return {"n": n, "steps": steps, "engine": engine, "last_level": last_level, "core": core,
            "per_fmu_step": per_step, "valgrind_notes": notes}


def callgrind_series(ns: Sequence[int], fmu_steps: int = 2500, last_levels: Sequence[str | None] = (L2,),
                     cores: dict[str, str | None] | None = None, fmu_dir: Path = DEFAULT_OUT,
                     progress: Progress | None = None, engines: Sequence[str] = ("native",)) -> dict[str, Any]:
    """``callgrind`` for every N (about ``fmu_steps`` FMU-steps each), engine, cache model and core build."""
    cores = cores or {"installed": None}
    plan = [(level, engine, n, label) for level in last_levels for engine in engines for n in ns
            for label in (cores if engine == "native" else ["installed"])]
    runs = []
    for level, engine, n, label in plan:
        result = callgrind(n, max(1, fmu_steps // (n + 1)), level, cores.get(label), fmu_dir, engine)
        result["core_label"] = label
        runs.append(result)
        if progress is not None:
            p = result["per_fmu_step"]
            progress(len(runs), len(plan), f"callgrind {engine:<6} N={n:<4} LL={level or 'detected'} {label}: "
                     + " ".join(f"{event}={p[event]:.0f}" for event in ("Ir", "Ir_master", "D1mr", "DLmr", "I1mr")))
    return {"n": list(ns), "fmu_steps": fmu_steps, "last_levels": list(last_levels), "engines": list(engines),
            "cores": cores, "runs": runs}


def callgrind_markdown(result: dict[str, Any]) -> str:
    rows = []
    for run in result["runs"]:
        p = run["per_fmu_step"]
        last_level = p["DLmr"] + p["DLmw"]
        last_level_master = p["DLmr_master"] + p["DLmw_master"]
        rows.append([run.get("engine", "native"), run["n"], run["last_level"] or "detected", run["core_label"],
                     f"{p['Ir']:.0f}", f"{p['Ir_master']:.0f}", f"{p['Dr'] + p['Dw']:.0f}", f"{p['I1mr']:.0f}",
                     f"{p['D1mr'] + p['D1mw']:.0f}", f"{last_level:.0f}", f"{last_level_master:.0f}"])
    return ("callgrind, stepping only, per FMU-step: instructions, data accesses, simulated misses (L1 instruction, "
            "L1 data, last level); \"master\": outside the FMUs' fmi2SetReal / fmi2DoStep / fmi2GetReal\n\n"
            + markdown_table(["engine", "N", "last level (--LL)", "core", "instructions", "of which master",
                              "data accesses", "I1 misses", "D1 misses", "LL misses", "of which master"], rows))


def compare_cores(cores: dict[str, str], ns: Sequence[int], steps: int, rounds: int, fmu_dir: Path = DEFAULT_OUT,
                  progress: Progress | None = None) -> dict[str, Any]:
    """The native engine with two (or more) builds of _core.c, interleaved in fresh interpreters."""
    if len(cores) < 2:
        raise BenchUsageError(f"cores: give at least two LABEL=PATH builds to compare, got {len(cores)}")
    fmu_files(fmu_dir)
    folder = str(Path(fmu_dir).resolve())

    def measure(n: int, label: str) -> dict[str, Any]:
        result = run_child({"kind": "step", "engine": "native", "n": n, "steps": steps, "core": cores[label],
                            "fmu_dir": folder})
        result["core_label"] = label
        return result

    def describe(result: dict[str, Any]) -> str:
        return (f"N={result['n']:<4} {result['core_label']:<16} {result['us_per_fmu_step']:8.2f} µs/FMU-step "
                f"(CPU {result['cpu_us_per_fmu_step']:.2f})")

    samples = interleaved(rounds, ns, list(cores), measure, describe, progress)
    medians = {key: {label: {n: statistics.median(s[key] for s in samples if s["n"] == n and s["core_label"] == label)
                             for n in ns} for label in cores}
               for key in ("us_per_fmu_step", "cpu_us_per_fmu_step")}
    return {"n": list(ns), "steps": steps, "rounds": rounds, "cores": cores, "medians": medians, "samples": samples}


def cores_markdown(result: dict[str, Any]) -> str:
    ns, labels = result["n"], list(result["cores"])
    rows = []
    for key, what in (("us_per_fmu_step", "wall"), ("cpu_us_per_fmu_step", "CPU")):
        by_label = result["medians"][key]
        for label in labels:
            rows.append([f"{label} ({what})", *(f"{by_label[label][n]:.1f}" for n in ns),
                         f"{by_label[label][ns[-1]] / by_label[label][ns[0]]:.2f}"])
        if len(labels) == 2:
            a, b = labels
            rows.append([f"{b} / {a} ({what})", *(f"{by_label[b][n] / by_label[a][n]:.2f}" for n in ns), ""])
    return (f"native engine, µs per FMU-step, median of {result['rounds']} interleaved rounds of {result['steps']} steps\n\n"
            + markdown_table(["core", *(f"N={n}" for n in ns), f"N={ns[-1]} / N={ns[0]}"], rows))


def run_suite(ns: Sequence[int] = DEFAULT_N, steps: int = 150, rounds: int = 5, repeats: int = 3,
              with_callgrind: bool = False, fmu_dir: Path = DEFAULT_OUT, progress: Progress | None = None) -> dict[str, Any]:
    """``platoon bench flatness``: the floor's orders and idle subset, and optionally callgrind."""
    if with_callgrind and shutil.which("valgrind") is None:
        raise BenchUsageError("--callgrind needs valgrind (apt-get install valgrind)")
    result: dict[str, Any] = {"orders": run(ns, steps, rounds, repeats, fmu_dir, progress)}
    if with_callgrind:
        result["callgrind"] = callgrind_series(ns, fmu_dir=fmu_dir, progress=progress, engines=("native", "python"))
    return result


def suite_markdown(result: dict[str, Any]) -> str:
    parts = [markdown(result["orders"])]
    if "callgrind" in result:
        parts.append(callgrind_markdown(result["callgrind"]))
    return "\n\n".join(parts)
