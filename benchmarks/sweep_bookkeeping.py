"""Suite ``sweep-bookkeeping``: what a sweep costs per run besides the runs themselves, against its size.

For each size (10^2 .. 10^5 points by default) a real sweep of configs/paper/platoon.toml (both laws x
N/2 random draws of platoon.k_v: the sweep file is the same size for every N) goes through the real runner and output folder (orchestrator/sweep: plan made point by
point, trace moved into place, result file written and synced, row appended to results.csv, tables
rebuilt at start and end), with an executor that answers each run at once, leaving a small placeholder
trace (``TRACE_BYTES``), instead of simulating it. The wall time divided by the points is the per-run
bookkeeping; flat means it does not grow with the sweep (it once grew with the square of the runs).

Each measurement is a fresh interpreter (benchmarks/child.py) that first runs a 10-point sweep
(imports, the first config validation: start-up, not bookkeeping), then resets its peak resident set
size (Linux ``/proc/self/clear_refs``) and times the sweep: the peak RSS is the sweep's own. Most of a
run's bookkeeping is waiting for fsync, which other work on the disk slows down: the smallest size is
measured again before every larger one and after the last, and the ratio is the largest size's per-run
cost over the median of those references. CPU time per run is reported beside the wall time.
Also: how long a 10^6-point sweep takes from reading its file to its first run handed to the
executor (``--first-run``), disk check included.
"""

from __future__ import annotations

import resource
import statistics
import tempfile
import time
from pathlib import Path
from typing import Any, Iterator

from .common import PAPER_CONFIGS, BenchUsageError, Progress, markdown_table, run_child

BASE = PAPER_CONFIGS / "platoon.toml"
TRACE_BYTES = 4096  # the placeholder trace each instant run leaves: moved into traces/ like a real one
WARM_UP_POINTS = 10


class _Instant:
    """An executor whose every run completes at once (the bookkeeping is what is measured)."""

    name = "instant"

    def __init__(self, stop_after: int | None = None) -> None:
        self.first: float | None = None
        self.stop_after = stop_after
        self.stopped = False
        self.runs_peak_kib: int | None = None  # peak RSS once every run is committed, before the end's tables

    def outcomes(self, jobs: Iterator[Any]) -> Iterator[tuple[Any, dict[str, Any]]]:
        placeholder = bytes(TRACE_BYTES)
        for number, job in enumerate(jobs, 1):
            if self.first is None:
                self.first = time.perf_counter()
            with open(job.partial_trace, "wb") as trace:  # what a run's trace writer leaves behind
                trace.write(placeholder)
            yield job, {"status": "completed", "wall_time": 0.0, "metrics": {"last.path_offset": 0.0}}
            if self.stopped or (self.stop_after is not None and number >= self.stop_after):
                break
        self.runs_peak_kib = _peak_rss_kib()  # the runner asked for more: the last run is committed

    def stop(self) -> None:  # SIGINT or SIGTERM (run_sweep's handler): no more runs
        self.stopped = True

    def close(self) -> None:
        pass


class _Quiet:
    def started(self, *args: Any) -> None:
        pass

    def finished(self, *args: Any) -> None:
        pass


def _sweep_file(folder: Path, points: int, random_draws: bool) -> Path:
    """A grid of ``points`` k_v values, or (``random_draws``) both laws x N/2 random k_v draws."""
    path = folder / f"sweep-{points}.toml"
    if random_draws:
        path.write_text(f'base = "{BASE.resolve()}"\n[grid]\n"platoon.law" = ["regular", "sine"]\n'
                        f'[random]\nsamples = {points // 2}\nseed = 1\n[random.ranges]\n"platoon.k_v" = [0.3, 1.0]\n')
    else:
        values = ", ".join(f"{0.5 + index * 1e-6:.6f}" for index in range(points))
        path.write_text(f'base = "{BASE.resolve()}"\n[grid]\n"platoon.k_v" = [{values}]\n')
    return path


def _sweep(folder: Path, points: int, stop_after: int | None = None) -> tuple[float, float, int | None]:
    """(wall time of the whole sweep, time from reading its file to its first run handed out, peak RSS in
    KiB once every run was committed: before the tables are rebuilt at the end)."""
    from orchestrator.sweep.plan import count, runs, value_columns
    from orchestrator.sweep.runner import run_sweep
    from orchestrator.sweep.spec import load_sweep
    from orchestrator.sweep.store import OutputFolder

    path = _sweep_file(folder, points, random_draws=True)  # a sweep file of the same size for every size
    executor = _Instant(stop_after)
    started = time.perf_counter()
    spec = load_sweep(path)
    # allow_full_disk: 10^6 runs' traces would not fit on most disks; the estimate is made all the same
    run_sweep(runs(spec), count(spec), OutputFolder(folder / f"out-{points}"), executor, folder, _Quiet(),
              varied=value_columns(spec), allow_full_disk=True)
    return time.perf_counter() - started, (executor.first or started) - started, executor.runs_peak_kib


def _peak_rss_kib() -> int:
    """VmHWM (peak resident set size) of this process, KiB, since start or the last ``_reset_peak``."""
    try:
        with open("/proc/self/status") as status:
            for line in status:
                if line.startswith("VmHWM:"):
                    return int(line.split()[1])
    except OSError:
        pass
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss  # KiB on Linux; never reset


def _reset_peak() -> None:
    try:
        with open("/proc/self/clear_refs", "w") as clear:
            clear.write("5")  # Linux >= 4.0: VmHWM := VmRSS
    except OSError:
        pass


def measure(points: int, first_run_only: bool = False) -> dict[str, Any]:
    """One size in this (fresh) interpreter: warm up, then time the sweep and its peak RSS."""
    with tempfile.TemporaryDirectory(prefix="bench-sweep-bookkeeping-") as scratch:  # TMPDIR picks the disk
        (Path(scratch) / "warm").mkdir()
        _sweep(Path(scratch) / "warm", WARM_UP_POINTS)
        _reset_peak()
        before_rss = _peak_rss_kib()
        cpu = time.process_time()
        folder = Path(scratch) / "measured"
        folder.mkdir()
        wall, first, runs_peak = _sweep(folder, points, stop_after=1 if first_run_only else None)
        cpu = time.process_time() - cpu
        # read before the folder is removed: shutil.rmtree lists each folder whole (a DirEntry per file), so
        # removing 2 x 10^5 files (10^5 results and traces) raised the peak by 16 MiB, which the sweep never uses
        peak = _peak_rss_kib()
    return {"points": points, "wall_time": wall, "per_run": wall / points, "cpu_per_run": cpu / points,
            "first_run_after": first, "rss_before_mib": before_rss / 1024, "peak_rss_mib": peak / 1024,
            "runs_peak_rss_mib": runs_peak / 1024 if runs_peak is not None else None}


def run(sizes: list[int], first_run_points: int, progress: Progress | None = None) -> dict[str, Any]:
    if not BASE.is_file():
        raise BenchUsageError(f"{BASE}: not found (run the benchmark from the repository)")
    reference, larger = sizes[0], sizes[1:]
    steps = [reference]
    for points in larger:
        steps += [points, reference]
    references, rows = [], []
    for number, points in enumerate(steps, 1):
        row = run_child({"kind": "sweep-bookkeeping", "points": points, "fmu_dir": "."}, timeout=24 * 3600.0)
        (references if points == reference and number % 2 == 1 else rows).append(row)
        if progress is not None:
            progress(number, len(steps), f"{points} points: {row['wall_time']:.2f} s, {1e3 * row['per_run']:.3f} ms "
                                         f"per run ({1e3 * row['cpu_per_run']:.3f} ms CPU), peak RSS {row['peak_rss_mib']:.0f} MiB")
    base = statistics.median(r["per_run"] for r in references)
    base_cpu = statistics.median(r["cpu_per_run"] for r in references)
    summary = {**references[0], "per_run": base, "cpu_per_run": base_cpu,
               "wall_time": statistics.median(r["wall_time"] for r in references)}
    rows = [summary, *rows]
    first = (run_child({"kind": "sweep-bookkeeping", "points": first_run_points, "first_run_only": True, "fmu_dir": "."})
             if first_run_points else None)
    return {"sizes": rows, "references": references, "ratio": rows[-1]["per_run"] / base,
            "cpu_ratio": rows[-1]["cpu_per_run"] / base_cpu, "first_run_points": first_run_points,
            "first_run_after": first["first_run_after"] if first else None,
            "first_run_peak_rss_mib": first["peak_rss_mib"] if first else None}


def _mib(value: float | None) -> str:
    return "" if value is None else f"{value:.0f}"


def render(result: dict[str, Any]) -> str:
    base = result["sizes"][0]
    table = markdown_table(("points", "wall s", "ms per run", "vs smallest", "CPU ms per run", "peak RSS MiB",
                            "of which the runs"),
                           [(f"{r['points']:,}", f"{r['wall_time']:.2f}", f"{1e3 * r['per_run']:.3f}",
                             f"{r['per_run'] / base['per_run']:.2f}", f"{1e3 * r['cpu_per_run']:.3f}",
                             f"{r['peak_rss_mib']:.0f}", _mib(r.get("runs_peak_rss_mib"))) for r in result["sizes"]])
    repeats = ", ".join(f"{1e3 * r['per_run']:.3f}" for r in result["references"])
    first = (f"\nfirst run of a {result['first_run_points']:,}-point sweep handed out after "
             f"{result['first_run_after']:.3f} s (peak RSS {result['first_run_peak_rss_mib']:.0f} MiB)"
             if result["first_run_after"] is not None else "")
    return (f"sweep bookkeeping per run (instant runs), ratio largest/smallest {result['ratio']:.2f} "
            f"(CPU {result['cpu_ratio']:.2f}; the smallest size is the median of {len(result['references'])} "
            f"measurements, ms per run: {repeats})\n{table}{first}")
