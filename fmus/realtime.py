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
"""

from __future__ import annotations

import time

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
