"""Suite ``sweep``: the wall time of one sweep with 1, 2, ... local workers (and on a Dask LocalCluster),
and the speed-up over one worker.

The sweep: ``--runs`` runs of configs/paper/platoon.toml (four vehicles) for ``--stop-time`` simulated
seconds, each with a different k_v (all alike in cost). Every measurement is a real ``platoon sweep``
into a fresh folder, as a user runs it (start-up, FMU check, process per run, results.csv included);
variants interleaved, rotated each round, medians. ``dask``: the same sweep with ``--scheduler`` on a
LocalCluster on 127.0.0.1 with as many single-threaded worker processes as the most local workers.

The speed-up can only reach the number of idle cores: measure on a quiet machine.
"""

from __future__ import annotations

import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any


from .common import PAPER_CONFIGS, BenchError, BenchUsageError, Progress, interleaved, markdown_table

BASE = PAPER_CONFIGS / "platoon.toml"


def _sweep_file(folder: Path, runs: int, stop_time: float) -> Path:
    k_v = ", ".join(f"{0.5 + 0.05 * index:.2f}" for index in range(runs))
    path = folder / "bench-sweep.toml"
    path.write_text(f'base = "{BASE.resolve()}"\n[set]\n"simulation.stop_time" = {stop_time!r}\n'
                    f'[grid]\n"platoon.k_v" = [{k_v}]\n')
    return path


def _platoon() -> list[str]:
    return [sys.executable, "-c", "from orchestrator.cli import main; main()"]


def run(workers: list[int], runs: int, stop_time: float, rounds: int, dask: bool, progress: Progress | None = None) -> dict[str, Any]:
    if not BASE.is_file():
        raise BenchUsageError(f"{BASE}: not found (run the benchmark from the repository)")
    variants = [f"local-{n}" for n in workers] + ([f"dask-{max(workers)}"] if dask else [])
    with tempfile.TemporaryDirectory(prefix="bench-sweep-") as scratch_name:
        scratch = Path(scratch_name)
        sweep_file = _sweep_file(scratch, runs, stop_time)
        cluster = None
        if dask:
            try:
                from distributed import LocalCluster
            except ImportError:
                raise BenchUsageError("--dask needs Dask: pip install 'platoon-cosim[dask]'") from None
            cluster = LocalCluster(n_workers=max(workers), threads_per_worker=1, host="127.0.0.1",
                                   dashboard_address=None, processes=True)
        counter = iter(range(10**6))
        try:
            def measure(_group: Any, variant: str) -> dict[str, Any]:
                kind, count = variant.split("-")
                options = ["--workers", count] if kind == "local" else ["--scheduler", cluster.scheduler_address]
                out = scratch / f"out-{next(counter)}"
                started = time.perf_counter()
                done = subprocess.run([*_platoon(), "sweep", str(sweep_file), "--out", str(out), "-q", *options],
                                      capture_output=True, text=True, timeout=3600)
                wall = time.perf_counter() - started
                if done.returncode != 0:
                    raise BenchError(f"{variant}: platoon sweep exit {done.returncode}: {done.stderr[-2000:]}")
                return {"variant": variant, "wall_time": wall}

            samples = interleaved(rounds, [None], variants, measure,
                                  lambda s: f"{s['variant']}: {s['wall_time']:.2f} s", progress)
        finally:
            if cluster is not None:
                cluster.close()
    medians = {v: statistics.median(s["wall_time"] for s in samples if s["variant"] == v) for v in variants}
    one = medians.get("local-1")
    return {"runs": runs, "stop_time": stop_time, "rounds": rounds, "samples": samples, "medians": medians,
            "speedup": {v: one / t for v, t in medians.items()} if one else {}}


def render(result: dict[str, Any]) -> str:
    rows = [(variant, f"{wall:.2f}", f"{wall / result['runs']:.2f}",
             f"{result['speedup'][variant]:.2f}" if variant in result["speedup"] else "-")
            for variant, wall in result["medians"].items()]
    title = f"sweep of {result['runs']} runs ({result['stop_time']:g} s simulated each), medians of {result['rounds']} rounds"
    return title + "\n" + markdown_table(("variant", "wall s", "s per run", "speed-up vs local-1"), rows)
