"""Will the sweep's files fit? An estimate of the disk it still needs, checked before its first run.

A sweep of 10^6 points writes 10^6 traces: at a megabyte each it needs a terabyte, and finding out when
the disk is full, hours in, helps nobody. Before the first run, the runs left times one run's files
(its trace, its result file, its row) is compared with the free space of the output folder's
filesystem (``shutil.disk_usage``: what this user may write); a sweep that does not fit is refused in
one line with both numbers, unless ``--allow-full-disk`` (then it runs until the disk is full and
stops there, every committed run kept: store.py).

One run's trace is estimated from its config: (steps / trace_every + 1) rows of each of its
components (the vehicles and the virtual target) at ``TRACE_BYTES_PER_ROW``, measured on the paper's
platoon (zstd-compressed rows: 195 B per vehicle-row, less for the target; see docs/sweeps.md), and of
each link FMU the wiring makes ([links]) at ``LINK_BYTES_PER_ROW``, so the estimate errs on the large
side by about 10 %. The first point of the plan stands for all: a grid
that varies the platoon's length or the run's duration needs more or less than this says.
"""

from __future__ import annotations

import shutil
from pathlib import Path

from orchestrator.scenario.config import Config
from orchestrator.scenario.raw_config import recorded_rows

from .spec import SweepError

TRACE_BYTES_PER_ROW = 200  # compressed bytes per component per recorded row (measured: 195 B per vehicle)
# a link FMU's channel ([links]: two per vehicle): measured 72-75 B per link-row with a new beacon every
# step (paper platoon, 20 s, 2001 rows, links.delay = 0.05: 4 vehicles 1,762,136 B without links,
# 2,954,782 B with their 8 links; 12 vehicles 4,645,346 B and 8,127,701 B with 24). The links sit in
# chunks of their own (docs/trace-format.md, "Chunk groups"), away from the vehicles whose numbers they
# repeat: interleaved with them they had compressed to 41 B. Held beacons (a period) repeat and take less.
LINK_BYTES_PER_ROW = 80
BLOCK = 4096  # a file takes whole blocks of the filesystem (ext4, tmpfs: 4 KiB)
RESULT_OVERHEAD = 2048  # bytes of a result file besides its resolved config (values, metrics, overrides)
ROW_BYTES = 512  # a results.csv row with a dozen vehicles' metrics, and its share of results.parquet
ALLOW_FULL_DISK = "--allow-full-disk"


def _blocks(size: int) -> int:
    return -(-size // BLOCK) * BLOCK


def run_bytes(config: Config) -> int:
    """The disk one run of ``config`` takes: its trace, its result file (whole blocks each), its row."""
    rows = recorded_rows(config.steps, config.simulation.trace_every)
    trace = rows * ((config.platoon.count + 1) * TRACE_BYTES_PER_ROW + len(config.linked()) * LINK_BYTES_PER_ROW)
    result = len(config.model_dump_json()) * 2 + RESULT_OVERHEAD  # indented JSON: about twice the compact text
    return _blocks(trace) + _blocks(result) + ROW_BYTES


def _size(count: float) -> str:
    for unit in ("B", "KB", "MB", "GB", "TB"):
        if count < 1000 or unit == "TB":
            return f"{count:.0f} {unit}" if unit == "B" else f"{count:.1f} {unit}"
        count /= 1000
    raise AssertionError("unreachable")


def free_bytes(folder: Path) -> int:
    """What this user may still write on ``folder``'s filesystem (the folder exists)."""
    return shutil.disk_usage(folder).free


def check_space(folder: Path, config: Config | None, runs_left: int, allow_full_disk: bool = False) -> None:
    """Raise ``SweepError`` (one line, both numbers) when ``runs_left`` runs of ``config`` need more disk
    than ``folder``'s filesystem has free. ``config`` None (the first point is invalid): nothing to estimate."""
    if config is None or runs_left <= 0:
        return
    per_run = run_bytes(config)
    needed, free = per_run * runs_left, free_bytes(folder)
    if needed > free and not allow_full_disk:
        raise SweepError(f"--out {folder}: {runs_left:,} runs need about {_size(needed)} ({_size(per_run)} each: "
                         f"trace and result), the disk has {_size(free)} free; free some space, make the sweep "
                         f"smaller (simulation.trace_every records fewer rows), or pass {ALLOW_FULL_DISK} to run "
                         f"until the disk is full")
