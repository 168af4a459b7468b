"""What tracing every step costs a run: the same scenario untraced, traced in process, traced by a second process.

    python -m benchmarks.trace_overhead         # paper platoon, N = 4 16 64, 1000 steps, 5 rounds
    python -m benchmarks.trace_overhead --vehicles 16 --steps 5000 --rounds 3
    python -m benchmarks.trace_overhead --engine python --vehicles 4

Every measurement is a fresh interpreter (``benchmarks.child``, task ``trace-overhead``)
running ``run_scenario`` once (as ``platoon run`` does, ``scenarios.run_config``), so no
run warms the next; rounds are interleaved (every variant once per round, the order rotating) and
medians are compared. The cost of a variant is what a user waits for once the FMUs are initialized:
the stepping loop plus finishing (FMUs closed, trace finalized, the second process's backlog
encoded), from ``RunResult.timings``; it is given per FMU-step (seconds / (steps x (N + 1))). The
worker's CPU time is reported too: the second process is not free, it uses the second core.

Variants (all with every channel: components, errors, Foxglove scene at 10 Hz, transforms, log):

* ``off``: no trace (``out=None``);
* ``inline``: the trace encoded in the stepping process (``--trace-writer inline``);
* ``process``: encoded by a second process (``--trace-writer process``, what ``auto`` picks for long runs).

Results go to runs/bench/trace-overhead.json (run it from the repository: the paper's config, the
FMUs and the results are found there).
"""

from __future__ import annotations

import argparse
import resource
import statistics
import sys
import tempfile
from pathlib import Path
from typing import Any, Sequence

from fmus.builders import DEFAULT_OUT

from .common import DEFAULT_OUT_DIR, PAPER_CONFIGS, BenchError, Progress, interleaved, run_child, write_result
from .platoon import fmu_files
from .scenarios import run_config

VARIANTS = ("off", "inline", "process")
PAPER = PAPER_CONFIGS / "platoon.toml"
RESULT_FILE = DEFAULT_OUT_DIR / "trace-overhead.json"  # one file, overwritten: rename it to keep a run


def traced_run(config: Path, variant: str, engine: str, vehicles: int, steps: int, out_dir: Path,
               fmu_dir: Path) -> dict[str, Any]:
    """Child side: one measured run of ``config`` (the paper platoon) in this fresh interpreter."""
    out = None if variant == "off" else out_dir / f"{variant}-{vehicles}.mcap"
    _, result = run_config(config, engine, out, [f"platoon.count={vehicles}", "path.radius=2000.0",
                                                 f"simulation.stop_time={steps * 0.01}"],
                           fmu_dir, trace_writer="inline" if variant == "off" else variant)
    if result.status != "completed":
        raise BenchError(f"{variant}: run {result.status}: {result.error}")
    children = resource.getrusage(resource.RUSAGE_CHILDREN)  # the trace writer process, once it has exited
    timings = result.timings
    return {"variant": variant, "n": vehicles, "steps": result.steps, "components": vehicles + 1,
            "run": timings["steps"] + timings["finish"], "steps_phase": timings["steps"], "finish": timings["finish"],
            "initialize": timings["initialize"], "worker_cpu": children.ru_utime + children.ru_stime,
            "trace_bytes": out.stat().st_size if out is not None else 0}


def run(ns: Sequence[int] = (4, 16, 64), steps: int = 1000, rounds: int = 5, engine: str = "native",
        fmu_dir: Path = DEFAULT_OUT, progress: Progress | None = None) -> dict[str, Any]:
    """Every variant at every N, once per round (interleaved, fresh interpreters); medians per FMU-step."""
    if not PAPER.is_file():
        raise BenchError(f"no {PAPER} in {Path.cwd()} (run from the repository)")
    fmu_files(fmu_dir)
    task = {"kind": "trace-overhead", "config": str(PAPER.resolve()), "engine": engine, "steps": steps,
            "fmu_dir": str(Path(fmu_dir).resolve())}

    def describe(result: dict[str, Any]) -> str:
        return f"N = {result['n']}: {result['variant']} {result['run']:.3f} s"

    with tempfile.TemporaryDirectory(prefix="trace-overhead-") as scratch:
        samples = interleaved(rounds, ns, VARIANTS,
                              lambda n, variant: run_child({**task, "variant": variant, "n": n, "out_dir": scratch}),
                              describe, progress)
    summary: dict[int, dict[str, dict[str, Any]]] = {}
    for n in ns:
        row = {}
        for variant in VARIANTS:
            runs = [s for s in samples if s["n"] == n and s["variant"] == variant]
            fmu_steps = runs[0]["steps"] * runs[0]["components"]
            row[variant] = {
                "us_per_fmu_step": statistics.median(r["run"] for r in runs) / fmu_steps * 1e6,
                "finish_s": statistics.median(r["finish"] for r in runs),
                "worker_cpu_s": statistics.median(r["worker_cpu"] for r in runs),
                "trace_mb": runs[0]["trace_bytes"] / 1e6,
                "runs_s": [r["run"] for r in runs],
            }
        off = row["off"]["us_per_fmu_step"]
        for variant in VARIANTS:
            row[variant]["ratio_to_off"] = row[variant]["us_per_fmu_step"] / off
        summary[n] = row
    return {"engine": engine, "steps": steps, "rounds": rounds, "results": summary, "samples": samples}


def table(result: dict[str, Any]) -> str:
    """The medians per FMU-step and the ratios to ``off``, one line per N."""
    lines = ["per FMU-step, median [µs] of (stepping + finishing); ratio to 'off' in the same run",
             f"{'N':>4}{'off':>9}{'inline':>9}{'ratio':>7}{'process':>9}{'ratio':>7}"
             f"{'finish [s]':>12}{'worker CPU [s]':>16}{'trace [MB]':>12}"]
    for n, row in result["results"].items():
        lines.append(f"{n:>4}{row['off']['us_per_fmu_step']:>9.1f}{row['inline']['us_per_fmu_step']:>9.1f}"
                     f"{row['inline']['ratio_to_off']:>7.2f}"
                     f"{row['process']['us_per_fmu_step']:>9.1f}{row['process']['ratio_to_off']:>7.2f}"
                     f"{row['process']['finish_s']:>12.3f}{row['process']['worker_cpu_s']:>16.2f}"
                     f"{row['process']['trace_mb']:>12.2f}")
    return "\n".join(lines)


def main() -> int:
    parser = argparse.ArgumentParser(prog="python -m benchmarks.trace_overhead", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--vehicles", type=int, nargs="+", default=[4, 16, 64])
    parser.add_argument("--steps", type=int, default=1000, help="steps of 0.01 s")
    parser.add_argument("--rounds", type=int, default=5)
    parser.add_argument("--engine", choices=["native", "python"], default="native")
    args = parser.parse_args()
    print(f"{args.engine} engine, paper platoon on R = 2000 m, {args.steps} steps of 0.01 s, "
          f"{args.rounds} interleaved rounds, a fresh interpreter per run", flush=True)

    def show(done: int, total: int, line: str) -> None:
        print(f"  {line}", flush=True)

    try:
        result = run(args.vehicles, args.steps, args.rounds, args.engine, progress=show)
    except BenchError as error:
        raise SystemExit(f"error: {error}") from None
    print()
    print(table(result))
    print(f"\nresults: {write_result(DEFAULT_OUT_DIR, 'trace-overhead', result, RESULT_FILE)}")
    return 0


if __name__ == "__main__":
    sys.exit(main())  # the FMUs ran in the children: this interpreter's teardown is safe
