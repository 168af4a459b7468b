"""Wall-clock pacing for runs with live components, and the record of how well it kept time.

With a live robot in the platoon, simulated time must be wall time: communication point t_k is
reached at wall time origin + t_k, never earlier. The master calls ``wait_until(t_k)`` after it has
stepped the components and before it reads outputs that describe t_k (a live component's outputs are
the robot's pose at that instant). ``lateness`` per point is how long after its deadline the master
got going again (the step jitter); an *overrun* is a point whose work was not done by its deadline,
so the master could not wait at all. The schedule never shifts: after a stall the master catches up.
``fell_behind`` adds up how far the run fell behind, once per stall (each rise of the lateness from one
point to the next), so two stalls of 0.1 s count 0.2 s, and one stall caught up over many points counts
once: while a run is behind, a live robot keeps moving on its last command, and the way it covers
meanwhile is what separates the platoon from an all-simulated one. A point late by no more than
``WAKE_UP_JITTER`` is the OS waking the master a little late, not a stall: nothing of it carries to the next
point, so it adds nothing (counted, it made an undisturbed 20 s run "0.15-0.28 s behind" from sub-millisecond
rises alone, and a held-out test's 0.2 s limit read that as stall time); its lateness is in the jitter.

``PacingPriority`` puts the one thread that keeps such a schedule (a live run's stepping thread, an emulated
robot's timing loop) at a real-time priority, when ``PLATOON_REALTIME_PRIORITY`` asks for it: see its docstring;
``pacing_helper`` puts the threads that hand it poses or commands one level below.
"""

from __future__ import annotations

import os
import threading
import time
from typing import Mapping

from fmus.component import percentile_summary

WAKE_UP_JITTER = 0.001  # s: lateness up to this is a late wake-up, not a stall (module docstring)


class Pacer:
    """Keeps a run on the wall clock; ``start()`` makes the current instant simulated time ``start_time``."""

    def __init__(self, clock=time.perf_counter, sleep=time.sleep) -> None:
        self.clock, self.sleep = clock, sleep
        self.origin = 0.0
        self.start_time = 0.0
        self.lateness: list[float] = []  # s after each point's deadline the master resumed
        self.overruns = 0
        self.worst_overrun = 0.0
        self.fell_behind = 0.0  # s: the sum of every rise of the lateness past a late wake-up (module docstring)
        self._last_target: float | None = None

    def start(self, start_time: float = 0.0) -> None:
        self.origin = self.clock()
        self.start_time = start_time

    def wait_until(self, t: float) -> None:
        """Return at wall time origin + (t - start_time), or at once if that has passed (an overrun)."""
        if t == self._last_target:  # several live components read outputs at one point: wait once
            return
        self._last_target = t
        deadline = self.origin + (t - self.start_time)
        now = self.clock()
        if now > deadline:
            self.overruns += 1
            self.worst_overrun = max(self.worst_overrun, now - deadline)
        else:
            remaining = deadline - now
            if remaining > 0.0005:
                self.sleep(remaining - 0.0003)  # the OS wakes us a little late: sleep short, finish by polling
            while self.clock() < deadline:
                pass
            now = self.clock()
        late = now - deadline
        if late > WAKE_UP_JITTER:
            self.fell_behind += max(0.0, late - (self.lateness[-1] if self.lateness else 0.0))
        self.lateness.append(late)

    def summary(self) -> dict[str, float]:
        """Step jitter (median, p99, max lateness, s), overruns and the worst one, and how far the run fell
        behind in all (s), for the trace and the table."""
        jitter = percentile_summary("jitter", self.lateness)
        jitter.pop("jitter.count", None)
        return {"points": len(self.lateness), **jitter, "overruns": self.overruns, "overrun.max": self.worst_overrun,
                "behind.total": self.fell_behind}


PRIORITY_VARIABLE = "PLATOON_REALTIME_PRIORITY"  # unset, empty or 0: paced threads keep the normal scheduler


class PacingPriority:
    """The calling thread, and only it, at real-time priority (``SCHED_FIFO``) while it keeps a wall-clock schedule,
    if ``PLATOON_REALTIME_PRIORITY`` names one (1-99); undone by ``restore``.

    Why one thread and not the process (``chrt -r 1 platoon run``): a paced thread sleeps most of each step, and
    at the normal scheduler a busy process beside it (a build, a test suite) delays its wake-up by milliseconds to
    tens of them, so the run falls behind its schedule. A whole process at one real-time priority protects it from
    those, but not from itself: its other threads (Zenoh's, the trace's) and the other processes started at the same
    priority do not preempt each other, and a woken pacing thread waited up to a 100 ms round-robin time slice
    behind one of them (docs/hil.md, "Accuracy"). Here only the thread that keeps time is raised: it preempts every
    normal thread the moment it wakes, and, as ``SCHED_RESET_ON_FORK`` makes the threads and processes it starts
    afterwards begin at the normal scheduler, it raises nothing else.

    Not permitted (no root, no ``CAP_SYS_NICE``, no rtprio limit: ``ulimit -r``), not a priority, or an OS
    without per-thread real-time scheduling: the thread stays as it was and ``note`` says why, in one line, for
    the caller's log; so does a granted one (its level is ``level``). Unset: nothing happens and ``note`` is None.
    A paced loop that never sleeps (a run that cannot keep up) keeps one core to itself at this priority: the
    kernel's real-time throttling (``/proc/sys/kernel/sched_rt_runtime_us``, 95 % by default) still leaves the
    rest of the machine a share of that core.
    """

    def __init__(self, what: str, environ: Mapping[str, str] = os.environ) -> None:
        self.note: str | None = None
        self.level = "Info"
        self._thread: int | None = None  # the raised thread's id, for restore from any thread
        self._previous: tuple[int, int] = (0, 0)  # its policy and priority before
        wanted = _asked(environ)
        if wanted in ("", "0"):
            return
        self.level = "Warning"
        asked = f"{PRIORITY_VARIABLE}={wanted}"
        if not hasattr(os, "sched_setscheduler"):
            self.note = f"{asked}: this OS has no per-thread real-time scheduling; {what} keeps the normal scheduler"
            return
        highest = os.sched_get_priority_max(os.SCHED_FIFO)
        if not wanted.isdigit() or not 1 <= int(wanted) <= highest:
            self.note = f"{asked}: expected a real-time priority 1-{highest} (or 0: none); {what} keeps the normal scheduler"
            return
        priority = int(wanted)
        previous = (os.sched_getscheduler(0), os.sched_getparam(0).sched_priority)
        try:
            _calling_thread_to_fifo(priority)
        except PermissionError:
            self.note = (f"{asked}: real-time priority not permitted here (it needs root, CAP_SYS_NICE or an rtprio "
                         f"limit: `ulimit -r`); {what} keeps the normal scheduler, and may fall behind on a busy machine")
            return
        except OSError as error:
            self.note = f"{asked}: real-time priority refused ({error}); {what} keeps the normal scheduler"
            return
        self._thread, self._previous = threading.get_native_id(), previous
        self.level = "Info"
        self.note = f"{what} at real-time priority (SCHED_FIFO {priority}, {asked}); the threads it starts are not"

    @property
    def raised(self) -> bool:
        return self._thread is not None

    def restore(self) -> None:
        """The raised thread back at the scheduler it had (from any thread; once raised, once undone): what it
        does after its schedule (closing links, finalizing) must not hold a core at real-time priority."""
        thread, self._thread = self._thread, None
        if thread is None:
            return
        policy, priority = self._previous
        try:
            os.sched_setscheduler(thread, policy & ~os.SCHED_RESET_ON_FORK, os.sched_param(priority))
        except ProcessLookupError:  # the thread has ended: nothing holds the priority any more
            pass


_helper = threading.local()  # per thread: whether pacing_helper has looked at it


def pacing_helper() -> None:
    """Called first in a callback the paced thread depends on (Zenoh's thread handing over a pose, a command):
    that thread, once, one real-time level under ``PLATOON_REALTIME_PRIORITY`` (none asked, or asked 1: left as is).

    Why: the callback holds the lock the paced thread reads the newest pose under, and Python's GIL; at the
    normal scheduler a busy process beside it can preempt it holding them, and the paced thread, though first
    in line for a core, then waits for both (measured: docs/hil.md, "Accuracy"). One level under, it is not
    preempted by anything at the normal scheduler, and it never delays the paced thread on a core. A refusal
    is silent here: ``PacingPriority`` says it once for the process."""
    if getattr(_helper, "seen", False):
        return
    _helper.seen = True
    wanted = _asked(os.environ)
    if not wanted.isdigit() or not hasattr(os, "sched_setscheduler"):
        return
    level = int(wanted) - 1
    if not 1 <= level < os.sched_get_priority_max(os.SCHED_FIFO):
        return
    try:
        _calling_thread_to_fifo(level)
    except OSError:
        pass


def _asked(environ: Mapping[str, str]) -> str:
    """What ``PLATOON_REALTIME_PRIORITY`` asks for, as written (stripped): the paced thread and its helpers read it."""
    return environ.get(PRIORITY_VARIABLE, "").strip()


def _calling_thread_to_fifo(priority: int) -> None:
    """The calling thread (0: this thread, for Linux's per-thread scheduling) at ``SCHED_FIFO`` ``priority``; what it
    starts afterwards begins at the normal scheduler (``SCHED_RESET_ON_FORK``). Raises ``OSError`` if refused."""
    os.sched_setscheduler(0, os.SCHED_FIFO | os.SCHED_RESET_ON_FORK, os.sched_param(priority))
