"""Memory and wall time of a long, big traced run: RSS sampled from inside while 100 vehicles run an hour.

    python -m benchmarks.trace_memory                          # configs/bench/platoon100-1h.toml
    python -m benchmarks.trace_memory --trace-every 1 --set simulation.stop_time=300   # every point
    python -m benchmarks.trace_memory --set simulation.stop_time=600   # a shorter look

Two promises are measured: RSS stays flat over a long run (the trace is written as the run goes, never
held in memory), and the wall time of a whole 100-vehicle, 1-hour simulated run with ``--trace-every``
(what a long study costs). The default run is therefore
configs/bench/platoon100-1h.toml (100 vehicles, 3600 s at 0.1 s, 1 Hz recording, every channel:
components, errors, Foxglove scene); docs/model.md ("Long platoons") says why that config and not
the paper's k_v = 0.5, under which a 100-vehicle platoon breaks down within minutes.

The run goes through ``orchestrator.execution.run.run_scenario``, as ``platoon run`` does, so what is measured
is what a user gets. Every ``--sample`` steps its progress callback reads VmRSS from
/proc/self/status (the callback runs in the stepping process), and the RSS of its children: the trace
writer process, which encodes and writes the trace when ``--trace-writer`` is ``process`` (what
``auto`` picks for this run). The result is a JSON file under runs/bench/: the samples, the RSS growth over the second half
of the run (after warm-up) per simulated and per wall-clock hour, the wall time, the trace's size and
chunk count (the chunk index, one small record per chunk kept until the summary is written, is the one
thing an indexed MCAP writer must hold for the whole run), and, read back from the trace, how far the
platoon strayed from its equilibrium (a run that blew up would make the memory numbers meaningless).
Run it from the repository: the config, the FMUs (build/fmus) and the result are found there.
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from fmus.builders import DEFAULT_OUT, PYTHONFMU
from orchestrator.scenario.config import Config, load_config
from orchestrator.execution.run import default_engine, run_scenario
from orchestrator.scenario.scenario import step_count

from .common import DEFAULT_OUT_DIR, rss_kib, slope, write_result

DEFAULT_CONFIG = Path("configs") / "bench" / "platoon100-1h.toml"


def rss_mb(pid: int | str = "self") -> float:
    """Resident set size of a process now, in MiB; 0 if it is gone (the writer process may exit
    between listing this process's children and reading its status)."""
    try:
        return rss_kib(pid) / 1024.0
    except FileNotFoundError:
        return 0.0


def children_rss_mb() -> float:
    """RSS of this process's children, in MiB: the trace writer process when the trace is encoded there."""
    pid = os.getpid()
    try:
        with open(f"/proc/{pid}/task/{pid}/children") as children:
            return sum(rss_mb(child) for child in children.read().split())
    except FileNotFoundError:
        return 0.0


def second_half_slopes(samples: list[dict[str, float]], stop_time: float, key: str = "rss_mb") -> tuple[float, float]:
    """Least-squares RSS slope over the samples in the run's second half (simulated time), in MiB
    per simulated hour and per wall-clock hour: the first half holds the warm-up (imports, FMU
    instantiation, first blocks and chunks), which is not growth."""
    late = [s for s in samples if s["t"] >= stop_time / 2.0]
    if len(late) < 3:
        return float("nan"), float("nan")
    t, wall, rss = ([s[name] for s in late] for name in ("t", "wall", key))
    return slope(t, rss)[1] * 3600.0, slope(wall, rss)[1] * 3600.0


def trace_summary(path: Path) -> tuple[int, int]:
    """Chunk count and rows on each component channel, from the MCAP summary section."""
    from mcap.reader import make_reader

    with open(path, "rb") as stream:
        summary = make_reader(stream).get_summary()
    return len(summary.chunk_indexes), max(summary.statistics.channel_message_counts.values())


def equilibrium_deviation(path: Path, config: Config) -> dict[str, object]:
    """Largest |speed - V_c|, |gap - d*| and |path error| over every vehicle and recorded point,
    and the vehicle with the largest speed deviation: the run is only a fair memory test if the
    platoon stayed a platoon. Imported here, after the run: the metrics are no part of its RSS."""
    from orchestrator.trace import load

    from .equilibrium_growth import deviations

    names, _, speeds, gaps, offsets = deviations(load(path), config)
    speed, gap, offset, worst = 0.0, 0.0, 0.0, ""
    for name, dv_row, gap_row, offset_row in zip(names, speeds, gaps, offsets):
        dv = float(np.max(dv_row))
        if dv >= speed:
            speed, worst = dv, name
        gap = max(gap, float(np.max(gap_row)))
        offset = max(offset, float(np.max(offset_row)))
    return {"speed_m_s": speed, "speed_worst_vehicle": worst, "gap_m": gap, "path_m": offset}


def _arguments() -> argparse.Namespace:
    parser = argparse.ArgumentParser(prog="python -m benchmarks.trace_memory", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--config", type=Path, default=DEFAULT_CONFIG, help="scenario TOML (default: %(default)s)")
    parser.add_argument("--set", dest="overrides", action="append", default=[], help="config override KEY=VALUE")
    parser.add_argument("--trace-every", type=int, default=None, help="record every K-th point (default: the config's)")
    parser.add_argument("--sample", type=int, default=200, help="sample RSS every this many steps")
    parser.add_argument("--engine", choices=("native", "python"), default=None, help="stepping core (default: native when built)")
    parser.add_argument("--trace-writer", choices=("auto", "inline", "process"), default="auto",
                        help="where the trace is encoded (as platoon run's option; default %(default)s)")
    parser.add_argument("--out", type=Path, default=None, help="keep the trace here (default: a temporary file, deleted)")
    parser.add_argument("--json", type=Path, default=None, help="result file (default: runs/bench/trace-memory-<time>.json)")
    return parser.parse_args()


def _report(args: argparse.Namespace, config, overrides: list[str], engine: str, steps: int, result, samples: list[dict[str, float]],
            rss_before: float, load_before, load_after, trace_bytes: int, chunks: int, rows: int, trace_writer: str,
            deviation: dict) -> dict:
    """The JSON result: the run, RSS (this process and the writer's) over time and its growth, the trace."""
    sim = config.simulation
    rss = np.array([s["rss_mb"] for s in samples])
    half = next((i for i, s in enumerate(samples) if s["t"] >= sim.stop_time / 2.0), len(samples) - 1)
    per_sim_hour, per_wall_hour = second_half_slopes(samples, sim.stop_time)
    writer_rss = np.array([s["writer_rss_mb"] for s in samples])
    writer_per_sim_hour, _ = second_half_slopes(samples, sim.stop_time, "writer_rss_mb")
    return {
        "config": str(args.config),
        "overrides": overrides,
        "vehicles": config.platoon.count,
        "stop_time_s": sim.stop_time,
        "step_s": sim.step,
        "max_substep_s": sim.max_substep,
        "steps": steps,
        "trace_every": sim.trace_every,
        "engine": engine,
        "status": result.status,
        "error": result.error,
        "wall_time_s": result.wall_time,
        "rss_before_run_mb": rss_before,
        "rss_first_sample_mb": float(rss[0]),
        "rss_at_half_time_mb": float(rss[half]),
        "rss_last_mb": float(rss[-1]),
        "rss_max_mb": float(rss.max()),
        "rss_growth_second_half_mb_per_sim_hour": per_sim_hour,
        "rss_growth_second_half_mb_per_wall_hour": per_wall_hour,
        "trace_writer": trace_writer,
        "writer_rss_first_sample_mb": float(writer_rss[0]),
        "writer_rss_last_mb": float(writer_rss[-1]),
        "writer_rss_max_mb": float(writer_rss.max()),
        "writer_rss_growth_second_half_mb_per_sim_hour": writer_per_sim_hour,
        "trace_bytes": trace_bytes,
        "chunks": chunks,
        "rows_per_component_channel": rows,
        "max_deviation_from_equilibrium": deviation,
        "load_average_before_after": [load_before, load_after],
        "sample_every_steps": args.sample,
        "samples": samples,
    }


def _print_report(report: dict, samples: list[dict[str, float]], destination: Path) -> None:
    r = report
    deviation = r["max_deviation_from_equilibrium"]
    print()
    print("RSS samples (every 10th):")
    print(f"{'step':>8}{'sim [s]':>10}{'wall [s]':>10}{'RSS [MB]':>10}{'writer [MB]':>13}")
    shown = list(range(0, len(samples), 10)) + ([len(samples) - 1] if (len(samples) - 1) % 10 else [])
    for i in shown:
        s = samples[i]
        print(f"{s['step']:>8}{s['t']:>10.0f}{s['wall']:>10.0f}{s['rss_mb']:>10.1f}{s['writer_rss_mb']:>13.1f}")
    print()
    print(f"RSS: before the run {r['rss_before_run_mb']:.1f} MB, first sample {r['rss_first_sample_mb']:.1f} MB, "
          f"at half time {r['rss_at_half_time_mb']:.1f} MB, last {r['rss_last_mb']:.1f} MB, max {r['rss_max_mb']:.1f} MB")
    print(f"growth over the second half: {r['rss_growth_second_half_mb_per_sim_hour']:+.2f} MB per simulated hour, "
          f"{r['rss_growth_second_half_mb_per_wall_hour']:+.2f} MB per wall hour")
    if r["trace_writer"] == "process":
        print(f"trace writer process: first sample {r['writer_rss_first_sample_mb']:.1f} MB, last {r['writer_rss_last_mb']:.1f} MB, "
              f"max {r['writer_rss_max_mb']:.1f} MB, growth over the second half "
              f"{r['writer_rss_growth_second_half_mb_per_sim_hour']:+.2f} MB per simulated hour")
    print(f"trace: {r['trace_bytes'] / 1e6:.1f} MB, {r['chunks']} chunks, {r['rows_per_component_channel']} rows on each component channel")
    print(f"largest deviation from the equilibrium: speed {deviation['speed_m_s']:.3g} m/s ({deviation['speed_worst_vehicle']}), "
          f"gap {deviation['gap_m']:.3g} m, path {deviation['path_m']:.3g} m")
    print(f"wall time {r['wall_time_s']:.0f} s; load average before {r['load_average_before_after'][0][0]:.2f}, "
          f"after {r['load_average_before_after'][1][0]:.2f}")
    print(f"wrote {destination}")

def main() -> int:
    args = _arguments()
    overrides = list(args.overrides)
    if args.trace_every is not None:
        overrides.append(f"simulation.trace_every={args.trace_every}")
    config, _ = load_config(args.config, overrides)
    sim = config.simulation
    engine = args.engine or default_engine()
    steps = step_count(sim.stop_time, sim.step)
    fmu_dir = DEFAULT_OUT
    PYTHONFMU.build(fmu_dir)

    scratch = None
    if args.out is None:
        scratch = tempfile.TemporaryDirectory(prefix="trace-memory-")
        out = Path(scratch.name) / "memory.mcap"
    else:
        out = args.out
        out.parent.mkdir(parents=True, exist_ok=True)
    samples: list[dict[str, float]] = []
    started = time.perf_counter()

    next_sample = [args.sample]

    def tick(k: int) -> None:  # called after every call into the stepping core (tens of steps), not every step
        if k >= next_sample[0]:
            next_sample[0] = (k // args.sample + 1) * args.sample
            size = out.stat().st_size if out.exists() else 0
            samples.append({"step": k, "t": k * sim.step, "wall": time.perf_counter() - started,
                            "rss_mb": rss_mb(), "writer_rss_mb": children_rss_mb(), "trace_bytes": size})
            if len(samples) % 10 == 1:
                s = samples[-1]
                print(f"  step {k:>7}  t = {s['t']:>7.0f} s  wall {s['wall']:>6.0f} s  "
                      f"RSS {s['rss_mb']:>7.1f} MB (+ writer {s['writer_rss_mb']:>6.1f} MB)  trace {size / 1e6:>7.2f} MB",
                      flush=True)

    rss_before = rss_mb()
    load_before = os.getloadavg()
    print(f"{args.config.name}: {config.platoon.count} vehicles, {sim.stop_time:g} s simulated at {sim.step:g} s "
          f"({steps} steps), trace_every {sim.trace_every}, {engine} engine; RSS before the run {rss_before:.1f} MB",
          flush=True)
    result = run_scenario(config, args.config.read_text(), out, engine=engine, fmu_dir=fmu_dir, tick=tick,
                          trace_writer=args.trace_writer)
    load_after = os.getloadavg()
    trace_bytes = out.stat().st_size
    print(f"run {result.status} in {result.wall_time:.0f} s; trace {trace_bytes / 1e6:.2f} MB", flush=True)

    chunks, rows = trace_summary(out)
    from orchestrator.trace import load

    trace_writer = load(out).metadata["platoon.start"].get("trace_writer", "inline")
    deviation = equilibrium_deviation(out, config)
    if scratch is not None:
        scratch.cleanup()
    report = _report(args, config, overrides, engine, steps, result, samples, rss_before, load_before, load_after,
                     trace_bytes, chunks, rows, trace_writer, deviation)
    destination = write_result(DEFAULT_OUT_DIR, "trace-memory", report, args.json)  # + versions, machine, commit, time
    _print_report(report, samples, destination)
    if result.status != "completed":
        print(f"run {result.status}: {result.error}")
    return 0 if result.status == "completed" else 1


if __name__ == "__main__":
    code = main()
    sys.stdout.flush()
    os._exit(code)  # pythonfmu FMUs ran in this interpreter: skip its teardown (see orchestrator/cli/app.py)
