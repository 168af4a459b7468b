"""Suite ``coupling``: cost per FMU-step with coupling "hold" against "extrapolate" (what the
second-order coupling costs).

The same platoon and measurement as the ``steps`` suite, run once with every FMU's ``coupling``
parameter (config key ``simulation.coupling``) set to "extrapolate" (the default: the receiver moves
its inputs along the sender's rates, second order) and once to "hold" (inputs frozen over the step,
first order; docs/coupling.md). Both couplings and every engine run in the same interleaved rounds,
so the ratio hold / extrapolate is measured under the same conditions.
"""

from __future__ import annotations

import statistics
import time
from pathlib import Path
from typing import Any, Sequence

from fmus.builders import DEFAULT_OUT

from .common import Progress, markdown_table
from .engines import LABELS
from .platoon import COUPLINGS, STEP
from .steps import agreement, check_engines, measure_all

DEFAULT_ENGINES = ("native", "slaves")
DEFAULT_N = (4, 16, 64)


def run(engines: Sequence[str] = DEFAULT_ENGINES, ns: Sequence[int] = DEFAULT_N, steps: int = 1000, rounds: int = 5,
        fmu_dir: Path = DEFAULT_OUT, progress: Progress | None = None) -> dict[str, Any]:
    check_engines(engines)
    started = time.perf_counter()
    samples = measure_all(engines, ns, steps, rounds, COUPLINGS, fmu_dir, progress)
    medians = {coupling: {engine: {n: statistics.median(
        s["us_per_fmu_step"] for s in samples if s["engine"] == engine and s["n"] == n and s["coupling"] == coupling)
        for n in ns} for engine in engines} for coupling in COUPLINGS}
    ratios = {engine: {n: medians["hold"][engine][n] / medians["extrapolate"][engine][n] for n in ns} for engine in engines}
    return {
        "steps": steps, "step": STEP, "rounds": rounds, "n": list(ns), "engines": list(engines), "master": "jacobi",
        "couplings": list(COUPLINGS), "unit": "microseconds per FMU-step (wall time / (steps x (N + 1)))",
        "medians": medians, "hold_over_extrapolate": ratios,
        "final_position_agreement_m": agreement(samples, engines, ns),
        "samples": samples, "seconds": time.perf_counter() - started,
    }


def markdown(result: dict[str, Any]) -> str:
    ns, medians, ratios = result["n"], result["medians"], result["hold_over_extrapolate"]
    rows = []
    for engine in result["engines"]:
        for coupling in result["couplings"]:
            rows.append([LABELS[engine], coupling, *(f"{medians[coupling][engine][n]:.1f}" for n in ns)])
        rows.append([LABELS[engine], "**hold / extrapolate**", *(f"**{ratios[engine][n]:.2f}**" for n in ns)])
    return (f"µs per FMU-step by coupling, median of {result['rounds']} interleaved rounds, {result['steps']} steps of "
            f"{result['step']} s, Jacobi, 1 target + N vehicles\n\n"
            + markdown_table(["engine", "coupling", *(f"N={n}" for n in ns)], rows))
