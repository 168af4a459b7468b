"""Ctrl-C and SIGTERM during a run: stop between two steps, keep the trace.

``StopRequest`` holds the signal handlers for the length of a run; ``Interrupted`` is what a stop
raises at a communication point.
"""

from __future__ import annotations

import signal
import threading


class Interrupted(KeyboardInterrupt):
    """A run stopped by a signal (SIGINT or SIGTERM) at a communication point."""

    def __init__(self, signum: int) -> None:
        super().__init__(signal.Signals(signum).name)
        self.signum = signum


class StopRequest:
    """Signal handlers for the length of a run.

    The first SIGINT or SIGTERM only raises a flag, which the observer checks after recording each
    communication point: the run stops between two steps, never inside an FMU call (pythonfmu FMUs
    run Python code, where a KeyboardInterrupt would turn into an FMU error). A second signal while
    the loop still runs raises at once, in case a component hangs. After the loop, signals are only
    noted until the trace is finalized (except while waiting for a trace writer process, which a
    further signal stops: ``finishing``); then the previous handlers come back. A second signal raised
    inside an FMU call makes that call fail: ``forced`` tells the run it was an interruption.
    """

    SIGNALS = (signal.SIGINT, signal.SIGTERM)

    def __init__(self) -> None:
        self.signum = 0
        self.armed = False
        self.forced = False  # a second signal raised Interrupted, possibly inside an FMU call
        self.finishing = False  # waiting for the trace writer process: any further signal ends the wait
        self._previous: dict[int, object] = {}

    def _handler(self, signum: int, frame: object) -> None:
        if self.signum and (self.armed or self.finishing):
            self.forced = True
            raise Interrupted(signum)
        self.signum = self.signum or signum

    def check(self) -> None:
        """Raise ``Interrupted`` once a signal arrived: called between two steps (never inside an FMU)."""
        if self.signum:
            raise Interrupted(self.signum)

    def install(self) -> None:
        if threading.current_thread() is not threading.main_thread():
            return  # signal handlers can only be set from the main thread; the caller keeps its own
        for signum in self.SIGNALS:
            if signal.getsignal(signum) is signal.SIG_IGN:
                continue  # ignored by whoever started us (e.g. SIGINT for a background job): keep it so
            self._previous[signum] = signal.signal(signum, self._handler)
        self.armed = True

    def restore(self) -> None:
        self.armed = False
        for signum, handler in self._previous.items():
            signal.signal(signum, handler)
        self._previous.clear()
