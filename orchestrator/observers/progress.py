"""Progress of a long loop as the user sees it: a bar on a terminal, plain lines anywhere else.

A run piped to a file or a CI log has no terminal: rich's bar would print nothing (or, forced, a
garbled stream of redraws). There we write plain text lines to the same stream, at each tenth of the
work once at least ``PLATOON_PROGRESS_SECONDS`` (default 5 s) of wall time passed since the previous
line, so a short run prints none and a long one a line every tenth (or less often), each with the
elapsed and estimated remaining time. ``PLATOON_PROGRESS_SECONDS=0`` prints every tenth.
"""

from __future__ import annotations

import math
import os
import time
from contextlib import contextmanager
from pathlib import Path
from typing import Any, Callable, Iterator, Protocol, TextIO, runtime_checkable

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


def waiting_text(what: str, left: float) -> str:
    return f"waiting for {what}: {math.ceil(max(0.0, left))} s left before the run gives up"


def building_text(name: str, folder: Path) -> str:
    return f"building {name}.fmu in {folder}/ (once: later runs reuse it while its sources are unchanged)"


@runtime_checkable
class ProgressDisplay(Protocol):
    """What a run shows before and while it steps: FMUs being built, what its start waits for (with a
    countdown), then the progress of the steps, whose time estimates count from ``stepping()`` on."""

    def __call__(self, done: int) -> None: ...

    def building(self, name: str, folder: Path) -> None: ...

    def waiting(self, what: str, left: float) -> None: ...

    def stepping(self) -> None: ...


class ProgressLines:
    """``label: 30% (3000/10000 steps), 12 s elapsed, about 28 s left``: one line per tenth, at most one
    per ``min_gap`` seconds; the final 100 % line only when an earlier line was printed. The clock
    starts at ``stepping()`` (or the first tick): building FMUs or waiting for a robot is not stepping."""

    def __init__(self, total: int, label: str, unit: str, stream: TextIO, min_gap: float) -> None:
        self.total = max(1, total)
        self.label = label
        self.unit = unit
        self.stream = stream
        self.min_gap = min_gap
        self.started: float | None = None
        self.last_line = 0.0
        self.last_wait: float | None = None
        self.tenth = 0  # the last tenth reached
        self.printed = False

    def _write(self, line: str) -> None:
        self.stream.write(line + "\n")
        self.stream.flush()

    def building(self, name: str, folder: Path) -> None:
        self._write(building_text(name, folder))

    def waiting(self, what: str, left: float) -> None:
        now = time.perf_counter()  # called about each second: the first line, then at most one per min_gap
        if self.last_wait is None or now - self.last_wait >= self.min_gap:
            self.last_wait = now
            self._write(waiting_text(what, left))

    def stepping(self) -> None:
        if self.started is None:
            self.started = self.last_line = time.perf_counter()

    def __call__(self, done: int) -> None:
        self.stepping()
        tenth = min(TENTHS, done * TENTHS // self.total)
        if tenth <= self.tenth:
            return
        self.tenth = tenth
        now = time.perf_counter()
        if now - self.last_line < self.min_gap and not (tenth == TENTHS and self.printed):
            return
        elapsed = now - (self.started or now)
        left = "" if done >= self.total else f", about {_duration(elapsed * (self.total - done) / done)} left"
        self._write(f"{self.label}: {100 * done // self.total}% ({done}/{self.total} {self.unit}), "
                    f"{_duration(elapsed)} elapsed{left}")
        self.last_line = now
        self.printed = True


class ProgressBar:
    """A transient rich bar on a terminal, shown from ``stepping()`` (or the first tick) on; before it,
    a status line for what the start waits for, counting down."""

    def __init__(self, total: int, label: str, console) -> None:
        from rich.progress import BarColumn, Progress, TextColumn, TimeElapsedColumn, TimeRemainingColumn

        self.console, self.total = console, total
        self.bar = Progress(TextColumn("[bold]{task.description}"), BarColumn(), TextColumn("{task.percentage:>5.1f}%"),
                            TimeElapsedColumn(), TimeRemainingColumn(), console=console, transient=True)
        self.task = self.bar.add_task(label, total=total, start=False)
        self.every = max(1, total // 200)  # redraws are costly: at most ~200 updates
        self.status: Any = None
        self.shown = False

    def building(self, name: str, folder: Path) -> None:
        self.console.print(building_text(name, folder), highlight=False)

    def waiting(self, what: str, left: float) -> None:
        if self.status is None:
            self.status = self.console.status(waiting_text(what, left))
            self.status.start()
        else:
            self.status.update(waiting_text(what, left))

    def stepping(self) -> None:
        if self.shown:
            return
        self._stop_status()
        self.shown = True
        self.bar.start()
        self.bar.start_task(self.task)

    def __call__(self, done: int) -> None:
        self.stepping()
        if done % self.every == 0 or done == self.total:
            self.bar.update(self.task, completed=done)

    def _stop_status(self) -> None:
        if self.status is not None:
            self.status.stop()
            self.status = None

    def close(self) -> None:
        self._stop_status()
        if self.shown:
            self.bar.stop()


@contextmanager
def progress(total: int, label: str, console, quiet: bool = False,
             unit: str = "steps") -> Iterator[ProgressDisplay | None]:
    """A ``tick(done)`` for ``total`` units of work shown on ``console`` (a rich Console on stderr): a
    transient bar on a terminal, ``ProgressLines`` elsewhere, None when ``quiet``."""
    if quiet:
        yield None
        return
    if not console.is_terminal:
        yield ProgressLines(total, label, unit, console.file, progress_seconds())
        return
    bar = ProgressBar(total, label, console)
    try:
        yield bar
    finally:
        bar.close()


class LateProgress:
    """``tick(done, total)`` for work whose size is known only once it starts (a trace's chunks): shows
    nothing while the work is done within ``after`` seconds (most reads), then what ``progress`` shows.
    ``console``: a rich Console, or a function that makes one when it is first needed (rich then loads only
    for a read that shows a bar)."""

    def __init__(self, label: str, console, unit: str, after: float = 1.0) -> None:
        self.label, self.console, self.unit, self.after = label, console, unit, after
        self.started = time.perf_counter()
        self.display: Tick | None = None
        self.shown: Any = None

    def __call__(self, done: int, total: int) -> None:
        if self.display is None:
            if time.perf_counter() - self.started < self.after or done >= total:
                return
            console = self.console if hasattr(self.console, "is_terminal") else self.console()
            self.shown = progress(total, self.label, console, unit=self.unit)
            self.display = self.shown.__enter__()
        self.display(done)

    def close(self) -> None:
        if self.shown is not None:
            self.shown.__exit__(None, None, None)
            self.shown = self.display = None


@contextmanager
def late_progress(label: str, console, unit: str, after: float = 1.0) -> Iterator[LateProgress]:
    late = LateProgress(label, console, unit, after)
    try:
        yield late
    finally:
        late.close()


class ProgressObserver(Observer):
    """A run's progress as one of its observers: ``tick(k)`` as steps complete; with a
    ``ProgressDisplay``, also what the start waits for and when stepping starts."""

    def __init__(self, tick: Tick) -> None:
        self.tick = tick
        self.display = tick if isinstance(tick, ProgressDisplay) else None

    def waiting(self, what: str, left: float) -> None:
        if self.display is not None:
            self.display.waiting(what, left)

    def stepping(self) -> None:
        if self.display is not None:
            self.display.stepping()

    def advanced(self, steps_done: int) -> None:
        self.tick(steps_done)
