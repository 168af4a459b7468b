"""How long this process has existed (the part of a run's wall time spent before the run started), and
what a run's process sets up before its imports.

``platoon run -v`` splits a run's wall time into start-up (interpreter, imports, config, FMUs
checked and unpacked), the run's own phases and the summary. The interpreter's start is not
observable from Python, so it is read from the kernel: /proc/self/stat's start time (clock ticks since
boot) against /proc/uptime. Linux only; None elsewhere.
"""

from __future__ import annotations

import gc
import os
from contextlib import contextmanager
from typing import Iterator


def seconds_since_process_start() -> float | None:
    try:
        with open("/proc/self/stat") as stat:
            fields = stat.read().rsplit(")", 1)[1].split()
        with open("/proc/uptime") as uptime:
            now = float(uptime.read().split()[0])
    except (OSError, IndexError, ValueError):
        return None
    ticks = os.sysconf("SC_CLK_TCK")
    started = int(fields[19]) / ticks  # field 22 of stat; fields[0] here is field 3 (state)
    return max(0.0, now - started)


def single_threaded_blas() -> None:
    """Ask numpy's OpenBLAS for one thread, unless the user chose a number: call before numpy is imported.

    A run does no linear algebra, yet OpenBLAS starts a thread per core when numpy is imported: ~0.04 s
    of CPU and up to ~0.1 s of wall time in every run's start-up on a 2-core machine (docs/performance.md,
    "Whole runs"). The trace writer process inherits the setting. The analysis commands' matrices are
    small too (least squares over a few thousand rows, 15 x 15 eigenproblems): `platoon` sets it for
    every command (orchestrator/cli/launch.py).
    """
    os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")


@contextmanager
def loading_a_run() -> Iterator[None]:
    """Around the import of a run's modules (numpy, the engines, the trace writer): one BLAS thread,
    and no garbage collection while they load.

    What a process loads at start-up lives as long as the process, yet the collector traversed it
    again and again while it grew: ~0.05 s of a run's start-up, a full collection of ~0.02 s among it.
    On the way out, everything allocated so far is frozen (``gc.freeze``: kept out of all later
    collections), and collection resumes for what the run allocates. The price: garbage that start-up
    left in reference cycles is never freed (a CLI process ends with its run).
    """
    single_threaded_blas()
    collecting = gc.isenabled()
    gc.disable()
    try:
        yield
    finally:
        gc.freeze()
        if collecting:
            gc.enable()
