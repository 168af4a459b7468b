"""Suite ``sweep-bookkeeping``: what a sweep costs per run besides the runs themselves, against its size.

For each size (10^2 .. 10^5 points by default) a real sweep of configs/paper/platoon.toml (a grid on
platoon.k_v) goes through the real runner and output folder (orchestrator/sweep: plan made point by
point, result file written and synced, row appended to results.csv, tables rebuilt at start and end),
with an executor that answers each run at once instead of simulating it. The wall time divided by the
points is the per-run bookkeeping; flat means it does not grow with the sweep (issue 30: it grew with
the square of the runs). Also: how long a 10^6-point sweep takes from the command's start to its
first run handed to the executor (``--first-run``).
"""

from __future__ import annotations

import tempfile
import time
from pathlib import Path
from typing import Any, Iterator

from .common import PAPER_CONFIGS, BenchUsageError, Progress, markdown_table

BASE = PAPER_CONFIGS / "platoon.toml"


class _Instant:
    """An executor whose every run completes at once (the bookkeeping is what is measured)."""

    name = "instant"

    def __init__(self, stop_after: int | None = None) -> None:
        self.first: float | None = None
        self.stop_after = stop_after

    def outcomes(self, jobs: Iterator[Any]) -> Iterator[tuple[Any, dict[str, Any]]]:
        for number, job in enumerate(jobs, 1):
            if self.first is None:
                self.first = time.perf_counter()
            yield job, {"status": "completed", "wall_time": 0.0, "metrics": {"last.path_offset": 0.0}}
            if self.stop_after is not None and number >= self.stop_after:
                return

    def stop(self) -> None:
        pass

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


def _sweep(folder: Path, points: int, stop_after: int | None = None) -> tuple[float, float]:
    """(wall time of the whole sweep, time from reading its file to its first run handed out)."""
    from orchestrator.sweep.plan import count, runs, value_columns
    from orchestrator.sweep.runner import run_sweep
    from orchestrator.sweep.spec import load_sweep
    from orchestrator.sweep.store import OutputFolder

    path = _sweep_file(folder, points, random_draws=stop_after is not None)
    executor = _Instant(stop_after)
    started = time.perf_counter()
    spec = load_sweep(path)
    run_sweep(runs(spec), count(spec), OutputFolder(folder / f"out-{points}"), executor, folder, _Quiet(),
              varied=value_columns(spec))
    return time.perf_counter() - started, (executor.first or started) - started


def run(sizes: list[int], first_run_points: int, progress: Progress | None = None) -> dict[str, Any]:
    if not BASE.is_file():
        raise BenchUsageError(f"{BASE}: not found (run the benchmark from the repository)")
    rows = []
    with tempfile.TemporaryDirectory(prefix="bench-sweep-bookkeeping-") as scratch:
        for number, points in enumerate(sizes, 1):
            wall, _ = _sweep(Path(scratch), points)
            rows.append({"points": points, "wall_time": wall, "per_run": wall / points})
            if progress is not None:
                progress(number, len(sizes), f"{points} points: {wall:.2f} s, {1e3 * wall / points:.3f} ms per run")
        _, first = _sweep(Path(scratch), first_run_points, stop_after=1) if first_run_points else (0.0, None)
    base = rows[0]["per_run"]
    return {"sizes": rows, "ratio": rows[-1]["per_run"] / base, "first_run_points": first_run_points,
            "first_run_after": first}


def render(result: dict[str, Any]) -> str:
    table = markdown_table(("points", "wall s", "ms per run", "vs smallest"),
                           [(f"{r['points']:,}", f"{r['wall_time']:.2f}", f"{1e3 * r['per_run']:.3f}",
                             f"{r['per_run'] / result['sizes'][0]['per_run']:.2f}") for r in result["sizes"]])
    first = (f"\nfirst run of a {result['first_run_points']:,}-point sweep handed out after "
             f"{result['first_run_after']:.3f} s" if result["first_run_after"] is not None else "")
    return f"sweep bookkeeping per run (instant runs), ratio largest/smallest {result['ratio']:.2f}\n{table}{first}"
