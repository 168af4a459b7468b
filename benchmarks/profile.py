"""Suite ``profile``: where the native engine's time goes, in one process per N.

The native loop against the floor (the slave classes called directly), interleaved in one process;
the floor timed by phase; and, when ``perf`` is installed, perf's split of the native loop by shared
object and symbol (sampling, which works without hardware counters).
"""

from __future__ import annotations

import os
import shutil
import statistics
import subprocess
import tempfile
import time
from pathlib import Path
from typing import Any, Sequence

from fmus.builders import DEFAULT_OUT

from .common import Progress, run_child
from .floor import SlavePlatoon
from .platoon import STEP, fmu_files, scenario_for, unpacked_fmus

PROFILE_STEPS = 2000  # simulated 20 s at most per profile process


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


def profile(n: int, steps: int, rounds: int, fmu_dir: Path = DEFAULT_OUT) -> dict[str, Any]:
    """In one process: the native loop against the floor (interleaved), the floor's phases, and perf's
    split of the native loop by shared object and symbol (when perf is installed)."""
    from orchestrator.execution.native import NativeComponent, NativeMaster

    # Both platoons run rounds + 1 (floor) and rounds + 2 (native) samples one after the other: keep
    # that within 20 s of simulated time (a 64-vehicle platoon on the paper's circle loses string
    # stability and fails after about 28 s).
    steps = min(steps, PROFILE_STEPS // (rounds + 2))
    scenario = scenario_for(n, steps * (rounds + 2))
    fmus = unpacked_fmus(fmu_dir)
    master = NativeMaster([NativeComponent(s.name, fmus[s.fmu], s.parameters) for s in scenario.components],
                          scenario.connections)
    master.initialize(0.0)
    floor = SlavePlatoon(n, steps, fmu_dir=fmu_dir)
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


def describe(result: dict[str, Any]) -> str:
    n = result["n"]
    lines = [
        f"N = {n}, {result['steps']} steps per sample, {result['rounds']} interleaved samples, one process:",
        f"  native engine loop            {result['native_us']:6.2f} µs per FMU-step",
        f"  slave classes called directly {result['floor_us']:6.2f} µs per FMU-step (the floor)",
        f"  difference                    {result['native_us'] - result['floor_us']:6.2f} µs: the FMI boundary "
        "(pythonfmu's C++ wrapper, GIL state, its log buffer) and our loop, minus the floor's Python transfer",
        "  the floor by phase (µs per FMU-step, each including ~%.2f µs of timer): " % result["timer_us_per_call"]
        + ", ".join(f"{phase} {value:.2f}" for phase, value in result["floor_phases_us"].items()),
    ]
    if "perf_dso" in result:
        lines.append("  perf, native loop, by shared object: "
                     + ", ".join(f"{name} {share:.1f} %" for share, name in result["perf_dso"]))
        lines.append("  perf, top symbols:")
        lines += [f"    {share:5.1f} %  {name}" for share, name in result["perf_symbols"][:15]]
    return "\n".join(lines)


def run(ns: Sequence[int], steps: int = 1000, rounds: int = 3, fmu_dir: Path = DEFAULT_OUT,
        progress: Progress | None = None) -> dict[str, Any]:
    """One profile process per N (fresh interpreter each)."""
    fmu_files(fmu_dir)
    profiles = []
    for n in ns:
        profiles.append(run_child({"kind": "profile", "n": n, "steps": steps, "rounds": rounds,
                                   "fmu_dir": str(Path(fmu_dir).resolve())}))
        if progress is not None:
            progress(len(profiles), len(ns), f"N={n}: native {profiles[-1]['native_us']:.2f}, floor "
                                             f"{profiles[-1]['floor_us']:.2f} µs per FMU-step")
    return {"n": list(ns), "steps": steps, "rounds": rounds, "profiles": profiles}


def markdown(result: dict[str, Any]) -> str:
    return "\n\n".join(describe(p) for p in result["profiles"])
