"""What tracing costs a run: the same scenario without a trace, with the component channels only, and
with everything (component channels + Foxglove scene, transforms, errors, log), in one invocation.

    python benchmarks/trace_overhead.py                      # configs/paper/platoon.toml, 100 s, 5 rounds
    python benchmarks/trace_overhead.py --stop-time 20 --repeats 7 --set platoon.count=8

Rounds are interleaved (every variant once per round, the order rotating), and the medians of the
wall times reported by run_scenario (stepping, recording, encoding, closing the file; not the FMU
unpacking) are compared. Also prints each variant's trace size and message count.
"""

from __future__ import annotations

import argparse
import os
import statistics
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from fmus.build import DEFAULT_OUT, build_fmus  # noqa: E402
from orchestrator.config import load_config  # noqa: E402
from orchestrator.run import run_scenario  # noqa: E402
from orchestrator.trace import load  # noqa: E402

VARIANTS = {
    "no trace": dict(trace=False, foxglove=False),
    "components only": dict(trace=True, foxglove=False),
    "full trace": dict(trace=True, foxglove=True),  # what `platoon run` writes
}


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--config", type=Path, default=REPO / "configs" / "paper" / "platoon.toml")
    parser.add_argument("--stop-time", type=float, default=100.0)
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--set", dest="overrides", action="append", default=[], help="config override KEY=VALUE")
    args = parser.parse_args()

    fmu_dir = REPO / DEFAULT_OUT
    build_fmus(fmu_dir)
    config, _ = load_config(args.config, [*args.overrides, f"simulation.stop_time={args.stop_time}"])
    text = args.config.read_text()
    folder = Path(tempfile.mkdtemp(prefix="trace-overhead-"))
    times: dict[str, list[float]] = {name: [] for name in VARIANTS}
    cpus: dict[str, list[float]] = {name: [] for name in VARIANTS}  # CPU time of this process
    sizes: dict[str, tuple[int, int]] = {}
    names = list(VARIANTS)
    print(f"{config.name}: {config.platoon.count} vehicles, {args.stop_time:g} s at {config.simulation.step:g} s, "
          f"trace_every {config.simulation.trace_every}, {args.repeats} interleaved rounds", flush=True)
    for round_ in range(args.repeats):
        order = names[round_ % len(names):] + names[: round_ % len(names)]
        for name in order:
            variant = VARIANTS[name]
            out = folder / f"{name.replace(' ', '-')}.mcap" if variant["trace"] else None
            cpu = time.process_time()
            result = run_scenario(config, text, out, fmu_dir=fmu_dir, foxglove=variant["foxglove"])
            assert result.status == "completed", result.error
            times[name].append(result.wall_time)
            cpus[name].append(time.process_time() - cpu)
            if out is not None and name not in sizes:
                trace = load(out)
                sizes[name] = (out.stat().st_size, sum(info.messages for info in trace.topics.values()))
        print(f"  round {round_ + 1}: " + ", ".join(f"{n} {times[n][-1]:.2f} s" for n in names), flush=True)
    base = statistics.median(times["no trace"])
    steps = result.steps
    print()
    base_cpu = statistics.median(cpus["no trace"])
    print("wall: run_scenario's wall time, median; CPU: the process's CPU time over the same span, median")
    print(f"{'variant':<18}{'wall [s]':>10}{'ratio':>8}{'CPU [s]':>10}{'ratio':>8}{'trace [MB]':>12}{'messages':>10}")
    for name in names:
        median, cpu = statistics.median(times[name]), statistics.median(cpus[name])
        size, messages = sizes.get(name, (0, 0))
        print(f"{name:<18}{median:>10.3f}{median / base:>8.3f}{cpu:>10.3f}{cpu / base_cpu:>8.3f}"
              f"{size / 1e6:>12.2f}{messages:>10}")
    print(f"({steps} steps; wall per step without a trace {base / steps * 1e6:.0f} µs)")
    return 0


if __name__ == "__main__":
    code = main()
    sys.stdout.flush()
    os._exit(code)  # pythonfmu FMUs ran in this interpreter: skip its teardown (see orchestrator/cli.py)
