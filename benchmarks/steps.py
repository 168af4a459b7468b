"""Suite ``steps``: microseconds per FMU-step of our engines and the peers, N = 4 .. 256.

The platoon of ``platoon.scenario_for`` (1 target + N vehicles), Jacobi, steps of 0.01 s, run by
every engine of ``engines.ENGINES``, each measurement in a fresh interpreter, rounds interleaved
(every engine and N once per round, the engine order rotated each round). The result is the median
over rounds of wall time / (steps x (N + 1)), with the ratios against the peers taken from the same run, and
each engine's final positions compared with the native engine's (``agreement``): all masters must
be simulating the same system.
"""

from __future__ import annotations

import statistics
import time
from pathlib import Path
from typing import Any, Sequence

from fmus.builders import DEFAULT_OUT

from .common import BenchUsageError, Progress, interleaved, markdown_table, run_child
from .engines import ENGINES, LABELS, LIBCOSIM_ENGINES
from .platoon import STEP, fmu_files
from orchestrator.components.kinds import FMU_KINDS, fmu_folder, native_buildable

DEFAULT_ENGINES = ("native", "python", "fmpy-bare", "libcosim", "libcosim-0threads", "libcosim-0threads-lastvalue", "slaves")
DEFAULT_N = (4, 16, 64, 256)
NATIVE_FMUS = " + native FMUs"  # suffix of an engine's key when it steps the native FMUs
FMU_LESS_ENGINES = ("slaves",)  # engines that call the pythonfmu slave classes directly: no native twin
AGREEMENT = 1e-6  # m: libcosim's nanosecond grid differs from t_k = k h by ulps, nothing else may differ
RATIOS = (  # (name, numerator, denominator)
    ("native / libcosim-0threads (floor <= 1.0)", "native", "libcosim-0threads"),
    ("native-traced / native (floor <= 1.2)", "native-traced", "native"),
    ("native-offload / native (floor <= 1.2)", "native-offload", "native"),
    ("python / fmpy-bare (floor <= 0.8)", "python", "fmpy-bare"),
    ("native / slaves (overhead over the floor)", "native", "slaves"),
    ("native-buffer / native", "native-buffer", "native"),
    ("libcosim-0threads-lastvalue / libcosim-0threads (the old baseline's observer)", "libcosim-0threads-lastvalue",
     "libcosim-0threads"),
    ("native engine: native FMUs / pythonfmu FMUs (floor <= 1/30 = 0.0333)", "native" + NATIVE_FMUS, "native"),
    ("native FMUs: native engine / libcosim-0threads", "native" + NATIVE_FMUS, "libcosim-0threads" + NATIVE_FMUS),
    ("native FMUs: python engine / fmpy-bare", "python" + NATIVE_FMUS, "fmpy-bare" + NATIVE_FMUS),
    ("python engine: native FMUs / pythonfmu FMUs", "python" + NATIVE_FMUS, "python"),
    ("libcosim-0threads: native FMUs / pythonfmu FMUs", "libcosim-0threads" + NATIVE_FMUS, "libcosim-0threads"),
)


def engine_key(engine: str, fmus: str) -> str:
    """How results name an engine stepping FMUs of kind ``fmus`` (the pythonfmu runs keep the bare name)."""
    return engine + NATIVE_FMUS if fmus == "native" else engine


def base_engine(key: str) -> str:
    return key.removesuffix(NATIVE_FMUS)


def label(key: str) -> str:
    return LABELS[base_engine(key)] + (NATIVE_FMUS if key.endswith(NATIVE_FMUS) else "")


def fmu_kinds_to_measure(requested: Sequence[str] | None) -> tuple[str, ...]:
    """The FMU kinds a suite measures: the requested ones, else pythonfmu and (where buildable) native."""
    if requested is None:
        return ("python", "native") if native_buildable() else ("python",)
    unknown = [kind for kind in requested if kind not in FMU_KINDS]
    if unknown:
        raise BenchUsageError(f"unknown FMU kind(s) {', '.join(unknown)}; expected some of {', '.join(FMU_KINDS)}")
    if "native" in requested and not native_buildable():
        raise BenchUsageError("--fmus native: no C compiler here to build the native FMUs")
    return tuple(requested)


def check_engines(engines: Sequence[str]) -> None:
    """Unknown engines, or libcosim engines without libcosimpy installed, are a BenchError (a usage error)."""
    unknown = [e for e in engines if e not in ENGINES]
    if unknown:
        raise BenchUsageError(f"unknown engine(s) {', '.join(unknown)}; expected some of {', '.join(ENGINES)}")
    if any(e in LIBCOSIM_ENGINES for e in engines):
        import importlib.util

        if importlib.util.find_spec("libcosimpy") is None:
            raise BenchUsageError("the libcosim engines need libcosimpy (pip install -e '.[test]'), or leave them out")
    if any(e.startswith("native") for e in engines):
        from orchestrator.execution.native import available

        if not available():
            raise BenchUsageError("the native engines need the compiled core (reinstall with a C compiler: pip install -e .)")


def measure_all(engines: Sequence[str], ns: Sequence[int], steps: int, rounds: int, couplings: Sequence[str],
                fmu_dir: Path, progress: Progress | None, fmu_kinds: Sequence[str] = ("python",)) -> list[dict[str, Any]]:
    """Every (coupling, engine, FMU kind, N) once per round, in fresh interpreters, engine order rotated per
    round. A sample of native FMUs is named ``engine_key(engine, "native")``."""
    folders = {kind: str(fmu_folder(Path(fmu_dir), kind).resolve()) for kind in fmu_kinds}
    for folder in folders.values():
        fmu_files(Path(folder))  # build once, before any child needs them

    def measure(n: int, variant: tuple[str, str, str]) -> dict[str, Any]:
        coupling, engine, kind = variant
        result = run_child({"kind": "step", "engine": engine, "n": n, "steps": steps, "coupling": coupling,
                            "fmu_dir": folders[kind]})
        return {**result, "engine": engine_key(engine, kind), "fmus": kind}

    def describe(result: dict[str, Any]) -> str:
        what = result["engine"] if len(couplings) == 1 else f"{result['engine']} ({result['coupling']})"
        return f"N={result['n']:<4} {what:<30} {result['us_per_fmu_step']:8.2f} µs/FMU-step"

    variants = [(coupling, engine, kind) for coupling in couplings for kind in fmu_kinds for engine in engines
                if not (kind == "native" and engine in FMU_LESS_ENGINES)]
    return interleaved(rounds, ns, variants, measure, describe, progress)


def _medians(samples: list[dict[str, Any]], key: str, engines: Sequence[str], ns: Sequence[int],
             coupling: str) -> dict[str, dict[int, float]]:
    return {engine: {n: statistics.median(s[key] for s in samples
                                          if s["engine"] == engine and s["n"] == n and s["coupling"] == coupling)
                     for n in ns} for engine in engines}


def agreement(samples: list[dict[str, Any]], engines: Sequence[str], ns: Sequence[int]) -> dict[str, dict[int, float]]:
    """Largest |final position - the native engine's| per engine and N, same coupling, metres."""
    found: dict[str, dict[int, float]] = {}
    for s in samples:
        reference = next((r for r in samples if r["engine"] == "native" and r["n"] == s["n"]
                          and r["coupling"] == s["coupling"]), None)
        if reference is None:
            continue
        worst = max(abs(a - b) for name, values in s["final"].items()
                    for a, b in zip(values, reference["final"][name]))
        by_n = found.setdefault(s["engine"], {})
        by_n[s["n"]] = max(by_n.get(s["n"], 0.0), worst)
    return found


def run(engines: Sequence[str] = DEFAULT_ENGINES, ns: Sequence[int] = DEFAULT_N, steps: int = 1000, rounds: int = 5,
        fmu_dir: Path = DEFAULT_OUT, progress: Progress | None = None,
        fmu_kinds: Sequence[str] | None = None) -> dict[str, Any]:
    """The per-FMU-step table: samples, medians (wall and CPU), ratios, flatness in N, agreement.

    Each engine runs the pythonfmu FMUs and, in the same rounds, the native ones (``fmu_kinds``; default:
    both where a C compiler builds the native ones), named ``engine_key(engine, kind)``."""
    check_engines(engines)
    kinds = fmu_kinds_to_measure(fmu_kinds)
    started = time.perf_counter()
    samples = measure_all(engines, ns, steps, rounds, ["extrapolate"], fmu_dir, progress, kinds)
    measured = {s["engine"] for s in samples}
    engines = [engine_key(e, kind) for kind in kinds for e in engines if engine_key(e, kind) in measured]
    medians = _medians(samples, "us_per_fmu_step", engines, ns, "extrapolate")
    cpu_medians = _medians(samples, "cpu_us_per_fmu_step", engines, ns, "extrapolate")
    ratios = {name: {n: medians[a][n] / medians[b][n] for n in ns}
              for name, a, b in RATIOS if a in medians and b in medians}
    flatness = {engine: max(by_n.values()) / min(by_n.values()) for engine, by_n in medians.items()}
    growth = {engine: by_n[max(ns)] / by_n[min(ns)] for engine, by_n in medians.items()}
    # What one more vehicle costs per step, between successive N: flat if the per-vehicle cost is flat
    # in N. (The cost per FMU-step also moves because the one target is cheaper than a vehicle and its
    # share, 1 / (N + 1), shrinks.)
    pairs = list(zip(ns, ns[1:]))
    marginal = {engine: {f"{a}-{b}": (by_n[b] * (b + 1) - by_n[a] * (a + 1)) / (b - a) for a, b in pairs}
                for engine, by_n in medians.items()}
    agree = agreement(samples, engines, ns)
    disagreeing = {e: v for e, by_n in agree.items() for v in by_n.values() if v > AGREEMENT}
    return {
        "steps": steps, "step": STEP, "rounds": rounds, "n": list(ns), "engines": list(engines), "master": "jacobi",
        "fmu_kinds": list(kinds),
        "unit": "microseconds per FMU-step (wall time / (steps x (N + 1)))",
        "medians": medians, "cpu_medians": cpu_medians, "ratios": ratios,
        "flatness_max_over_min": flatness, "growth_largest_over_smallest_n": growth,
        "marginal_us_per_vehicle_step": marginal,
        "final_position_agreement_m": agree, "disagreeing": disagreeing,
        "gc_collections_in_timed_loops": sum(s["gc_collections"] for s in samples),
        "samples": samples, "seconds": time.perf_counter() - started,
    }


def _figure(value: float) -> str:
    """Three significant digits: 18.1 µs and 0.415 µs, and a ratio of 0.0286 against its floor 0.0333,
    read alike (one decimal showed the native FMUs as 0.4-0.6 and every ratio as 0.03)."""
    return f"{value:.0f}" if abs(value) >= 1000 else f"{value:.3g}"


def markdown(result: dict[str, Any]) -> str:
    ns, engines = result["n"], result["engines"]
    medians, cpu = result["medians"], result["cpu_medians"]
    header = ["engine", *(f"N={n}" for n in ns), f"N={ns[-1]} / N={ns[0]}", *(f"CPU N={n}" for n in ns)]
    rows = [[label(e), *(_figure(medians[e][n]) for n in ns), f"{result['growth_largest_over_smallest_n'][e]:.2f}",
             *(_figure(cpu[e][n]) for n in ns)] for e in engines]
    parts = [f"µs per FMU-step, median of {result['rounds']} interleaved rounds, {result['steps']} steps of "
             f"{result['step']} s, Jacobi, 1 target + N vehicles", markdown_table(header, rows)]
    if result["ratios"]:
        parts.append(markdown_table(["ratio (same run)", *(f"N={n}" for n in ns)],
                                    [[name, *(_figure(values[n]) for n in ns)] for name, values in result["ratios"].items()]))
    marginal = result["marginal_us_per_vehicle_step"]
    spans = list(next(iter(marginal.values()), {}))
    if spans:
        parts.append(markdown_table(["µs per step added by one more vehicle, between", *(f"N={span}" for span in spans)],
                                    [[label(e), *(_figure(marginal[e][span]) for span in spans)] for e in engines]))
    agree = result["final_position_agreement_m"]
    if agree:
        parts.append("largest |final position - native| per engine: " + ", ".join(
            f"{engine}: {max(by_n.values()):.1e} m" for engine, by_n in agree.items()))
    parts.append(f"garbage collections during the timed loops: {result['gc_collections_in_timed_loops']}")
    if result["disagreeing"]:
        parts.append(f"WARNING: engines disagree with the native engine by more than {AGREEMENT} m: {result['disagreeing']}")
    return "\n\n".join(parts)
