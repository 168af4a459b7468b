"""The trace as an observer of the run: every recorded point, log line and link message to the MCAP
writer (in this process, or in a worker process), and the file finalized with how the run ended.

The trace is the first observer of every run: the others see a point only once the trace holds it.
Its end decides the run's status: a non-finite output in the last buffered block, a worker process
that died or a disk that filled turn a run into a failure, and a second Ctrl-C while the worker
finishes the file into an interruption (``finalize``).
"""

from __future__ import annotations

import os
import signal
from pathlib import Path
from typing import TYPE_CHECKING, Any, Callable, Sequence

from fmus.errors import ComponentError
from orchestrator.observers.base import Observer
from orchestrator.trace.foxglove import SCENE_RATE, FoxgloveChannels, SceneSettings
from orchestrator.trace.format import BLOCK
from orchestrator.trace.worker import TraceProcess, TraceWorker, TraceWorkerError
from orchestrator.trace.writer_base import NullTraceWriter, TraceWriteError

if TYPE_CHECKING:
    from orchestrator.scenario.config import Config
    from orchestrator.trace.writer import TraceWriter

# Where the trace is encoded: "inline" in the stepping process, "process" in a second process
# (orchestrator/trace/worker.py), "auto": a second process when the machine has a spare core and the
# run records enough messages that encoding them outweighs the worker's start-up (about 0.5-1 s).
TRACE_WRITERS = ("auto", "inline", "process")
WORKER_MESSAGES = 10_000  # recorded rows x components from which "auto" picks "process" (docs/performance.md)
PACED_BLOCK = 1  # rows an inline writer of a paced run encodes at once: each at its point (open_trace_writer)
STALLED_WRITER_GRACE = 2.0  # s a trace writer process may take nothing after a second signal before it is stopped


def choose_trace_writer(requested: str, rows: int, components: int) -> str:
    """"inline" or "process" for a run recording ``rows`` points of ``components`` components."""
    if requested not in TRACE_WRITERS:
        raise ValueError(f"unknown trace writer {requested!r}; expected one of {', '.join(TRACE_WRITERS)}")
    if requested != "auto":
        return requested
    spare_core = (len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count() or 1) >= 2
    return "process" if spare_core and rows * components >= WORKER_MESSAGES else "inline"


def open_trace_writer(
    kind: str,
    path: Path,
    components: list[tuple[str, list[str]]],
    descriptions: dict[str, dict[str, str]] | None,
    config: "Config",
    every: int = 1,
    scene_rate: float = SCENE_RATE,
    foxglove: bool = True,
    process: TraceProcess | None = None,
    publish: Path | None = None,
    native: bool = False,
    paced: bool = False,
) -> "TraceWriter | TraceWorker":
    """A run's trace writer, encoding in this process ("inline") or in a worker ("process"): same file.

    ``foxglove`` adds the Foxglove channels at ``scene_rate``; ``process`` is a worker started earlier;
    ``publish``: the final path, ``path`` being the aside file renamed onto it once finalized;
    ``native``: float64 blocks (the native engine's) are encoded in C (orchestrator/trace/native_rows.py).
    ``paced``: the run keeps wall-clock time (a live robot in it), so the inline writer encodes each row at its
    own point (``PACED_BLOCK``) instead of a block's worth at once: a second of rows encoded in one point took
    7-16 ms of a 10 ms step, an overrun every second on an idle machine (`platoon run` of
    configs/hil/m3pi_live3.toml: 5-11 overruns in 10 s; each row at its point: none, the largest point 6 ms).
    """
    if kind == "process":
        return TraceWorker(path, components, descriptions, every=every, process=process, publish=publish,
                           foxglove=(SceneSettings.of(config), components, scene_rate) if foxglove else None,
                           native=native)
    from orchestrator.trace.writer import TraceWriter  # the MCAP writer: loaded only when this process writes

    return TraceWriter(path, components, descriptions, every=every, publish=publish, native=native,
                       block=PACED_BLOCK if paced else BLOCK,
                       foxglove=FoxgloveChannels(config, components, scene_rate) if foxglove else None)


def signal_text(signum: int) -> str:
    return "interrupted by SIGINT (Ctrl-C)" if signum == signal.SIGINT else f"terminated by {signal.Signals(signum).name}"


class TraceObserver(Observer):
    """Hands what the run records to its trace writer (``NullTraceWriter``: a run without a trace)."""

    def __init__(self, writer: "TraceWriter | TraceWorker | NullTraceWriter") -> None:
        self.writer = writer
        self.wants_rows = not isinstance(writer, NullTraceWriter)

    def point(self, t: float, outputs: Sequence[Sequence[float]]) -> None:
        self.writer.record(t, outputs)

    def block(self, rows: Any) -> None:
        self.writer.write_block(rows)

    def log(self, t: float, level: str, message: str) -> None:
        self.writer.log(t, level, message)

    def link(self, stream: str, t: float, fields: dict[str, float]) -> None:
        self.writer.live(stream, t, fields)

    def metadata(self, name: str, values: dict[str, Any]) -> None:
        self.writer.metadata(name, values)

    @property
    def encoder(self) -> str:
        """"native" when the trace's rows are encoded in C (orchestrator/trace/native_rows.py), else "python"."""
        return "native" if getattr(self.writer, "native", False) else "python"

    @property
    def in_a_process(self) -> bool:
        """The trace is encoded by a worker process (its end can be waited on, and stall)."""
        return isinstance(self.writer, TraceWorker)

    def stalled(self) -> bool:
        """The worker process took nothing for ``STALLED_WRITER_GRACE`` s (only after the user insisted)."""
        return self.in_a_process and self.writer.stalled(STALLED_WRITER_GRACE)

    def abandon(self) -> None:
        """Stop a worker that takes no data: its complete chunks stay on disk, recoverable."""
        self.writer.abandon("stopped: it took no data after a second signal")

    def finalize(self, status: str, error: str | None, failed_at: float | None, signum: int | None, engine: str,
                 master: str, log: Callable[[float, str, str], None] | None = None) -> tuple[str, str | None]:
        """Write the run's last log line and ``platoon.run`` record, and close the file; returns (status, error).

        ``log``: where the last log line goes (the run's observers, this trace among them; default: the
        trace only). A non-finite output in the last buffered block turns the run into a failure here. If
        the trace writer process died, the file keeps its complete chunks (recoverable) and the run is a failure.
        """
        writer = self.writer
        log = log or writer.log
        try:
            try:
                writer.flush()
            except ComponentError as failure:  # a non-finite output in the last block
                status, error, failed_at = "failed", str(failure), failure.time
            last = writer.last_time
            if status == "interrupted":
                error = f"{signal_text(signum or signal.SIGINT)} at t = {last if last is not None else 0.0:.6g} s"
                log(last or 0.0, "Warning", f"run {error}")
            elif status == "failed":
                log(failed_at if failed_at is not None else (last or 0.0), "Error", f"run failed: {error}")
            else:
                log(last or 0.0, "Info", f"run completed: {writer.rows_recorded} points recorded")
            run_record = {"status": status, "error": error or "", "engine": engine, "master": master,
                          "steps_recorded": writer.rows_recorded, "last_time": "" if last is None else repr(float(last))}
            if signum is not None:
                run_record["signal"] = signal.Signals(signum).name
            writer.metadata("platoon.run", run_record)
            writer.close()
        except TraceWorkerError as failure:
            if status != "interrupted":
                status, error = "failed", str(failure).splitlines()[0]
        except TraceWriteError as failure:  # e.g. a full disk: the file keeps its complete chunks
            status, error = "failed", str(failure)
        return status, error
