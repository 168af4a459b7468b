"""What the stepping process needs of a trace writer without loading the MCAP writer: the errors a
writer raises, the error for a non-finite output, and the writer that records nothing.

A run whose trace is encoded in a worker process (orchestrator/trace/worker.py) never imports
``writer`` (mcap, zstandard) in the stepping process: a run's start-up counts every import
(a sweep is made of short runs: docs/performance.md, "Start-up").
``writer`` re-exports these names.
"""

from __future__ import annotations

import math
from typing import Any, Sequence

from fmus.errors import ComponentError


def non_finite_error(components: Sequence[tuple[str, Sequence[str]]], row: Sequence[float]) -> ComponentError:
    """The error for a flat row ``[t, outputs...]`` holding a non-finite output: which component, which output."""
    time, position = float(row[0]), 1
    for name, outputs in components:
        for key in outputs:
            if not math.isfinite(row[position]):
                return ComponentError(name, time, f"output {key} = {row[position]} is not finite (the trace ends before it)")
            position += 1
    return ComponentError(components[0][0], time, "outputs overflow")


class TraceWriteError(OSError):
    """The trace file could not be written (disk full, file too large, I/O error): one line saying
    what happened and where the complete chunks written so far are."""


class NullTraceWriter:
    """Records nothing: ``run_scenario(..., out=None)`` runs with this (benchmarks, dry runs)."""

    foxglove = None
    recorded = 0
    rows_recorded = 0
    last_time = None

    def record(self, time: float, outputs: Sequence[Sequence[float]]) -> None:
        pass

    def write_block(self, rows: Any) -> None:
        pass

    def flush(self) -> None:
        pass

    def log(self, time: float, level: str, message: str) -> None:
        pass

    def live(self, stream: str, time: float, fields: dict[str, float]) -> None:
        pass

    def metadata(self, name: str, values: dict[str, Any]) -> None:
        pass

    def close(self) -> None:
        pass
