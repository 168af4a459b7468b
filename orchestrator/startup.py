"""How long this process has existed: the part of a run's wall time spent before the run started.

``platoon run -v`` splits a run's wall time into start-up (interpreter, imports, config, FMUs
checked and unpacked), the run's own phases and the summary. The interpreter's start is not
observable from Python, so it is read from the kernel: /proc/self/stat's start time (clock ticks since
boot) against /proc/uptime. Linux only; None elsewhere.
"""

from __future__ import annotations

import os


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
