"""Progress of a long loop as the user sees it: a bar on a terminal, plain lines anywhere else.

A run piped to a file or a CI log has no terminal: rich's bar would print nothing (or, forced, a
garbled stream of redraws). There we write plain text lines to the same stream, at each tenth of the
work once at least ``PLATOON_PROGRESS_SECONDS`` (default 5 s) of wall time passed since the previous
line, so a short run prints none and a long one a line every tenth (or less often), each with the
elapsed and estimated remaining time. ``PLATOON_PROGRESS_SECONDS=0`` prints every tenth.
"""

from __future__ import annotations

import os
import time
from contextlib import contextmanager
from typing import Callable, Iterator, TextIO

from orchestrator.observers.base import Observer

Tick = Callable[[int], None]  # called with the units done so far (steps), 1 .. total

PROGRESS_SECONDS_VARIABLE = "PLATOON_PROGRESS_SECONDS"
DEFAULT_PROGRESS_SECONDS = 5.0
TENTHS = 10


def progress_seconds() -> float:
    """Least wall time between two progress lines off a terminal (``PLATOON_PROGRESS_SECONDS``, >= 0)."""
    text = os.environ.get(PROGRESS_SECONDS_VARIABLE, "")
    try:
        value = float(text)
    except ValueError:
        return DEFAULT_PROGRESS_SECONDS
    return value if value >= 0 and value == value else DEFAULT_PROGRESS_SECONDS


def _duration(seconds: float) -> str:
    if seconds < 10:
        return f"{seconds:.1f} s"
    whole = int(round(seconds))
    return f"{whole // 60}:{whole % 60:02d} min" if whole >= 60 else f"{whole} s"


class ProgressLines:
    """``label: 30% (3000/10000 steps), 12 s elapsed, about 28 s left``: one line per tenth, at most one
    per ``min_gap`` seconds; the final 100 % line only when an earlier line was printed."""

    def __init__(self, total: int, label: str, unit: str, stream: TextIO, min_gap: float) -> None:
        self.total = max(1, total)
        self.label = label
        self.unit = unit
        self.stream = stream
        self.min_gap = min_gap
        self.started = time.perf_counter()
        self.last_line = self.started
        self.tenth = 0  # the last tenth reached
        self.printed = False

    def __call__(self, done: int) -> None:
        tenth = min(TENTHS, done * TENTHS // self.total)
        if tenth <= self.tenth:
            return
        self.tenth = tenth
        now = time.perf_counter()
        if now - self.last_line < self.min_gap and not (tenth == TENTHS and self.printed):
            return
        elapsed = now - self.started
        left = "" if done >= self.total else f", about {_duration(elapsed * (self.total - done) / done)} left"
        self.stream.write(f"{self.label}: {100 * done // self.total}% ({done}/{self.total} {self.unit}), "
                          f"{_duration(elapsed)} elapsed{left}\n")
        self.stream.flush()
        self.last_line = now
        self.printed = True


@contextmanager
def progress(total: int, label: str, console, quiet: bool = False, unit: str = "steps") -> Iterator[Tick | None]:
    """A ``tick(done)`` for ``total`` units of work shown on ``console`` (a rich Console on stderr): a
    transient bar on a terminal, ``ProgressLines`` elsewhere, None when ``quiet``."""
    if quiet:
        yield None
        return
    if not console.is_terminal:
        yield ProgressLines(total, label, unit, console.file, progress_seconds())
        return
    from rich.progress import BarColumn, Progress, TextColumn, TimeElapsedColumn, TimeRemainingColumn

    bar = Progress(TextColumn("[bold]{task.description}"), BarColumn(), TextColumn("{task.percentage:>5.1f}%"),
                   TimeElapsedColumn(), TimeRemainingColumn(), console=console, transient=True)
    task = bar.add_task(label, total=total)
    every = max(1, total // 200)  # redraws are costly: at most ~200 updates

    def tick(done: int) -> None:
        if done % every == 0 or done == total:
            bar.update(task, completed=done)

    bar.start()
    try:
        yield tick
    finally:
        bar.stop()


class ProgressObserver(Observer):
    """A run's progress as one of its observers: ``tick(k)`` as steps complete."""

    def __init__(self, tick: Tick) -> None:
        self.tick = tick

    def advanced(self, steps_done: int) -> None:
        self.tick(steps_done)
