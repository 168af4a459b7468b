"""The running summary: the per-vehicle summary of the rows the trace records (same decimation),
accumulated while stepping, so that `platoon run` prints its table without reading the trace again.

When the trace is written by a worker process, the folding runs on a thread of its own
(``on_thread``), fed copies of the recorded blocks through a short queue. Folding needs numpy (0.06 s
to import) and about 2.6 µs per row of 16 vehicles; done in the stepping thread at the first block,
it held up the trace writer process, which then waited for the next block (docs/performance.md,
"Start-up: what a run loads before its first step", the trace writer ready before the first step). The stepping thread spends most of such a run waiting for that process to take its
blocks, with the GIL released; the folding thread uses that time. The queue is short, so a folding
thread that falls behind holds the run back rather than its memory growing; ``finish`` waits for it
to fold every block. A run that encodes its trace itself (a sweep's) never waits like that: there
the thread only added switching (3.6 % of a traced N = 16 run), so it folds in the stepping thread.
"""

from __future__ import annotations

import queue
import threading
from typing import TYPE_CHECKING, Any, Sequence

from orchestrator.observers.base import Observer

if TYPE_CHECKING:
    from orchestrator.scenario.config import Config
    from orchestrator.analysis.metrics import RunningSummary, VehicleSummary

PENDING_BLOCKS = 8  # copied blocks that may wait for the folding thread


class SummaryObserver(Observer):
    """Feeds a ``RunningSummary`` the recorded rows, in blocks: in the stepping thread, or on a thread of
    its own (``on_thread``: when a worker process writes the trace)."""

    wants_rows = True
    BLOCK = 1024  # rows gathered from single points before the summary takes them

    def __init__(self, config: Config, components: list[tuple[str, list[str]]], steps: int, every: int,
                 on_thread: bool = False) -> None:
        step = config.simulation.step
        # the last recorded point is the last multiple of ``every`` steps; rows are every * step apart
        self._settings = (config, components, 0.0, (steps // every) * every * step, 0.5 * every * step)
        self.width = 1 + sum(len(outputs) for _, outputs in components)
        self.every = every
        self.summary: RunningSummary | None = None
        self._count = 0
        self._rows: list[float] = []
        self._blocks: queue.Queue[bytes | None] = queue.Queue(maxsize=PENDING_BLOCKS)
        self._thread: threading.Thread | None = None
        self._failure: BaseException | None = None
        self.on_thread = on_thread

    def point(self, t: float, outputs: Sequence[Sequence[float]]) -> None:
        if self._count % self.every == 0:
            self._rows.append(t)
            for values in outputs:
                self._rows.extend(values)
            if len(self._rows) >= self.BLOCK * self.width:
                self._flush()
        self._count += 1

    def block(self, rows: Any) -> None:
        if self.on_thread:
            self._hand_over(rows.tobytes())  # a copy: the engine refills its buffer
        else:
            self._fold_rows(rows.array() if hasattr(rows, "array") else rows)  # a RowBlock, or a 2-D array

    def _flush(self) -> None:
        if self._rows:
            from array import array

            self._hand_over(array("d", self._rows).tobytes())
            self._rows = []

    def _hand_over(self, data: bytes) -> None:
        if not self.on_thread:
            self._fold_block(data)
            return
        if self._thread is None:
            self._thread = threading.Thread(target=self._fold, name="running-summary", daemon=True)
            self._thread.start()
        self._blocks.put(data)

    def _fold_block(self, data: bytes) -> None:
        import numpy as np

        self._fold_rows(np.frombuffer(data, dtype=np.float64).reshape(-1, self.width))

    def _fold_rows(self, rows: Any) -> None:
        if self.summary is None:
            from orchestrator.analysis.metrics import running_summary

            config, components, start, expected_end, margin = self._settings
            self.summary = running_summary(config, components, start, expected_end, margin=margin)
        self.summary.add(rows)

    def _fold(self) -> None:
        try:
            while (data := self._blocks.get()) is not None:
                self._fold_block(data)
        except BaseException as error:  # noqa: BLE001  (raised by finish, in the run's thread)
            self._failure = error
            while self._blocks.get() is not None:  # keep taking blocks: the run must never wait on a dead thread
                pass

    def finish(self) -> None:
        """Fold every block handed over; raise what the folding thread raised."""
        self._flush()
        if self._thread is not None:
            self._blocks.put(None)
            self._thread.join()
            self._thread = None
        if self._failure is not None:
            failure, self._failure = self._failure, None
            raise failure

    def result(self) -> list[VehicleSummary] | None:
        self.finish()
        return self.summary.result() if self.summary is not None else None
