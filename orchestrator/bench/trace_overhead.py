"""What tracing every step costs a run: the same scenario untraced, traced in process, traced by a second process.

    python benchmarks/trace_overhead.py                         # paper platoon, N = 4 16 64, 1000 steps, 5 rounds
    python benchmarks/trace_overhead.py --vehicles 16 --steps 5000 --rounds 3
    python benchmarks/trace_overhead.py --engine python --vehicles 4

Every measurement is a fresh interpreter running ``run_scenario`` once (as ``platoon run`` does), so no
run warms the next; rounds are interleaved (every variant once per round, the order rotating) and
medians are compared. The cost of a variant is what a user waits for once the FMUs are initialized:
the stepping loop plus finishing (FMUs closed, trace finalized, the second process's backlog
encoded), from ``RunResult.timings``; it is given per FMU-step (seconds / (steps x (N + 1))). The
worker's CPU time is reported too: the second process is not free, it uses the second core.

Variants (all with every channel: components, errors, Foxglove scene at 10 Hz, transforms, log):

* ``off``: no trace (``out=None``);
* ``inline``: the trace encoded in the stepping process (``--trace-writer inline``);
* ``process``: encoded by a second process (``--trace-writer process``, what ``auto`` picks for long runs).

Results go to runs/bench/trace-overhead.json.
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

VARIANTS = ("off", "inline", "process")
PAPER = REPO / "configs" / "paper" / "platoon.toml"


def child(variant: str, engine: str, vehicles: int, steps: int, out_dir: Path) -> dict[str, float]:
    """One measured run in this (fresh) interpreter."""
    from fmus.build import DEFAULT_OUT
    from orchestrator.config import load_config
    from orchestrator.run import run_scenario

    config, _ = load_config(PAPER, [f"platoon.count={vehicles}", "path.radius=2000.0",
                                    f"simulation.stop_time={steps * 0.01}"])
    out = None if variant == "off" else out_dir / f"{variant}-{vehicles}.mcap"
    result = run_scenario(config, PAPER.read_text(), out, engine=engine, fmu_dir=REPO / DEFAULT_OUT,
                          trace_writer="inline" if variant == "off" else variant)
    if result.status != "completed":
        raise SystemExit(f"{variant}: run {result.status}: {result.error}")
    children = resource.getrusage(resource.RUSAGE_CHILDREN)
    timings = result.timings
    return {"steps": result.steps, "components": vehicles + 1, "run": timings["steps"] + timings["finish"],
            "steps_phase": timings["steps"], "finish": timings["finish"], "initialize": timings["initialize"],
            "worker_cpu": children.ru_utime + children.ru_stime,
            "trace_bytes": out.stat().st_size if out is not None else 0}


def measure(variant: str, engine: str, vehicles: int, steps: int, out_dir: Path) -> dict[str, float]:
    done = subprocess.run([sys.executable, __file__, "--child", variant, "--engine", engine, "--vehicles", str(vehicles),
                           "--steps", str(steps), "--out-dir", str(out_dir)], capture_output=True, text=True)
    if done.returncode != 0:
        raise SystemExit(f"{variant} N={vehicles} failed:\n{done.stderr}")
    return json.loads(done.stdout.strip().splitlines()[-1])


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--vehicles", type=int, nargs="+", default=[4, 16, 64])
    parser.add_argument("--steps", type=int, default=1000, help="steps of 0.01 s")
    parser.add_argument("--rounds", type=int, default=5)
    parser.add_argument("--engine", choices=["native", "python"], default="native")
    parser.add_argument("--child", choices=VARIANTS, help=argparse.SUPPRESS)
    parser.add_argument("--out-dir", type=Path, default=None, help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.child:
        print(json.dumps(child(args.child, args.engine, args.vehicles[0], args.steps, args.out_dir)))
        return 0

    from fmus.build import DEFAULT_OUT, build_fmus

    build_fmus(REPO / DEFAULT_OUT)
    folder = Path(tempfile.mkdtemp(prefix="trace-overhead-"))
    results: dict[int, dict[str, list[dict[str, float]]]] = {n: {v: [] for v in VARIANTS} for n in args.vehicles}
    print(f"{args.engine} engine, paper platoon on R = 2000 m, {args.steps} steps of 0.01 s, "
          f"{args.rounds} interleaved rounds, a fresh interpreter per run", flush=True)
    for round_ in range(args.rounds):
        for n in args.vehicles:
            order = VARIANTS[round_ % 3:] + VARIANTS[:round_ % 3]
            for variant in order:
                results[n][variant].append(measure(variant, args.engine, n, args.steps, folder))
            print(f"  round {round_ + 1}, N = {n}: " + ", ".join(
                f"{v} {results[n][v][-1]['run']:.3f} s" for v in VARIANTS), flush=True)
    summary = {}
    print()
    print("per FMU-step, median [µs] of (stepping + finishing); ratio to 'off' in the same run")
    print(f"{'N':>4}{'off':>9}{'inline':>9}{'ratio':>7}{'process':>9}{'ratio':>7}"
          f"{'finish [s]':>12}{'worker CPU [s]':>16}{'trace [MB]':>12}")
    for n in args.vehicles:
        row = {}
        for variant in VARIANTS:
            runs = results[n][variant]
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
        print(f"{n:>4}{off:>9.1f}{row['inline']['us_per_fmu_step']:>9.1f}{row['inline']['ratio_to_off']:>7.2f}"
              f"{row['process']['us_per_fmu_step']:>9.1f}{row['process']['ratio_to_off']:>7.2f}"
              f"{row['process']['finish_s']:>12.3f}{row['process']['worker_cpu_s']:>16.2f}"
              f"{row['process']['trace_mb']:>12.2f}")
    target = REPO / "runs" / "bench" / "trace-overhead.json"
    target.parent.mkdir(parents=True, exist_ok=True)
    target.write_text(json.dumps({"engine": args.engine, "steps": args.steps, "rounds": args.rounds,
                                  "cpus": os.cpu_count(), "when": time.strftime("%Y-%m-%dT%H:%M:%S"),
                                  "results": summary}, indent=2))
    print(f"\nresults: {target}")
    return 0


if __name__ == "__main__":
    code = main()
    sys.stdout.flush()
    os._exit(code)  # pythonfmu FMUs ran in this interpreter: skip its teardown (see orchestrator/cli.py)
