"""Memory over a long, big traced run: RSS sampled from inside while a 100-vehicle platoon runs.

    python benchmarks/trace_memory.py                                  # defaults below, about 4 min
    python benchmarks/trace_memory.py --vehicles 100 --stop-time 600 --step 0.05 --trace-every 20
    python benchmarks/trace_memory.py --trace-every 1 --stop-time 300  # every point: the heavy path

A 1-hour simulated run of 100 FMU vehicles at the paper's 0.01 s takes over an hour here (~11 ms
per step for 101 Python FMUs), and at coarser steps the 100-vehicle platoon breaks down (0.1 s: a
vehicle fails after ~200 s; 0.05 s: after ~680 s), hence 600 s at 0.05 s by default.

The run is configs/paper/platoon.toml on a circle of radius 2000 m (100 vehicles 75 m apart fit on
it without lapping), started on its equilibrium, traced with every channel (components, errors, Foxglove scene at 10 Hz of
simulated time, which decimation caps at the recording rate). Every ``--sample`` steps the progress
callback reads VmRSS from /proc/self/status. Prints the samples, then the RSS growth over the second
half of the run (after warm-up) per simulated hour and per wall-clock hour, and the trace's chunk
count, since the chunk index (one small record per chunk, kept until the summary is written) is the
one thing an indexed MCAP writer must keep in memory for the whole run.
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

import numpy as np  # noqa: E402

from fmus.build import DEFAULT_OUT, build_fmus  # noqa: E402
from orchestrator.config import load_config  # noqa: E402
from orchestrator.run import run_scenario  # noqa: E402


def rss_mb() -> float:
    with open("/proc/self/status") as status:
        for line in status:
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) / 1024.0
    raise RuntimeError("no VmRSS in /proc/self/status")


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--vehicles", type=int, default=100)
    parser.add_argument("--stop-time", type=float, default=600.0, help="simulated seconds")
    parser.add_argument("--step", type=float, default=0.05,
                        help="communication step, s")
    parser.add_argument("--trace-every", type=int, default=20, help="record every K-th point (default: 1 Hz)")
    parser.add_argument("--sample", type=int, default=200, help="sample RSS every this many steps")
    parser.add_argument("--out", type=Path, default=None, help="trace file (default: a temporary folder)")
    parser.add_argument("--set", dest="overrides", action="append", default=[], help="config override KEY=VALUE")
    args = parser.parse_args()

    fmu_dir = REPO / DEFAULT_OUT
    build_fmus(fmu_dir)
    paper = REPO / "configs" / "paper" / "platoon.toml"
    config, _ = load_config(paper, [
        f"platoon.count={args.vehicles}", "path.radius=2000.0", f"simulation.stop_time={args.stop_time}",
        f"simulation.step={args.step}", f"simulation.max_substep={args.step}",
        f"simulation.trace_every={args.trace_every}",
        # start on the equilibrium: the transient is not what this measures
        "initial.radial_offset=0.0", "initial.heading_error=0.0", "initial.speed_factor=1.0",
        *args.overrides,
    ])
    out = args.out or Path(tempfile.mkdtemp(prefix="trace-memory-")) / "memory.mcap"
    samples: list[tuple[int, float, float, float, int]] = []
    started = time.perf_counter()

    def tick(k: int) -> None:
        if k % args.sample == 0:
            size = out.stat().st_size if out.exists() else 0
            samples.append((k, k * args.step, time.perf_counter() - started, rss_mb(), size))
            if len(samples) % 10 == 1:
                print(f"  step {k:>7}  t = {k * args.step:>7.0f} s  wall {samples[-1][2]:>6.0f} s  "
                      f"RSS {samples[-1][3]:>7.1f} MB  trace {size / 1e6:>6.2f} MB", flush=True)

    print(f"{args.vehicles} vehicles, {args.stop_time:g} s simulated at {args.step:g} s "
          f"({int(round(args.stop_time / args.step))} steps), trace_every {args.trace_every}; RSS before the run "
          f"{rss_mb():.1f} MB", flush=True)
    result = run_scenario(config, paper.read_text(), out, fmu_dir=fmu_dir, tick=tick)
    print(f"run {result.status} in {result.wall_time:.0f} s; trace {out} {out.stat().st_size / 1e6:.2f} MB", flush=True)

    from mcap.reader import make_reader

    with open(out, "rb") as stream:
        summary = make_reader(stream).get_summary()
    chunks = len(summary.chunk_indexes)
    k, sim, wall, rss, _ = (np.array(column, dtype=float) for column in zip(*samples))
    half = len(k) // 2
    slope_sim = np.polyfit(sim[half:], rss[half:], 1)[0] * 3600.0
    slope_wall = np.polyfit(wall[half:], rss[half:], 1)[0] * 3600.0
    print()
    print("RSS samples (every 10th):")
    print(f"{'step':>8}{'sim [s]':>10}{'wall [s]':>10}{'RSS [MB]':>10}")
    for i in list(range(0, len(k), 10)) + ([len(k) - 1] if (len(k) - 1) % 10 else []):
        print(f"{int(k[i]):>8}{sim[i]:>10.0f}{wall[i]:>10.0f}{rss[i]:>10.1f}")
    print()
    print(f"RSS: first sample {rss[0]:.1f} MB, at half time {rss[half]:.1f} MB, last {rss[-1]:.1f} MB, "
          f"max {rss.max():.1f} MB")
    print(f"growth over the second half: {slope_sim:+.2f} MB per simulated hour, {slope_wall:+.2f} MB per wall hour")
    with open(out, "rb") as stream:
        rows = make_reader(stream).get_summary().statistics.channel_message_counts
    print(f"trace: {chunks} chunks ({chunks / max(result.wall_time, 1e-9):.2f} per wall second), "
          f"{max(rows.values())} rows on each component channel")
    if result.status != "completed":
        print(f"run {result.status}: {result.error}")
    return 0 if result.status == "completed" else 1


if __name__ == "__main__":
    code = main()
    sys.stdout.flush()
    os._exit(code)  # pythonfmu FMUs ran in this interpreter: skip its teardown (see orchestrator/cli.py)
