"""Does the robot answer its commands? A run that drives nothing must not say "completed".

A robot whose poses keep arriving but do not move while the run commands it to (the command topic
misspelled behind a DDS bridge, a base that listens to another topic, a robot whose driver ignores
this host) would otherwise let the run end with exit 0. ``MotionWatch`` compares, over the last
``WINDOW`` seconds of wall time, the way the run commanded (the commanded forward speed, each command
counted for at most its validity, so that a stall of the run, during which the robot rightly stops at
its deadline, is not blamed on the robot) with the way its measured poses moved (straight-line
distance between the first and the last pose of the window).

The thresholds, from the emulator's behaviour (docs/hil.md, "Commanded to move, not moving"): a robot
that answers moves at least ``MIN_RATIO`` of what it was commanded over any ``WINDOW`` once
``MIN_COMMANDED`` metres were asked of it; measured on the emulator's runs (m3pi dynamics, motor time
constant 0.05 s) the lowest ratio of a 10 s run was 0.97 (flying start, rmw_zenoh) and 0.89 (standing
start, 20 ms of latency both ways, 2 mm / 2 degrees of noise, the run 0.6 s behind on a loaded machine);
``motion.ratio_min`` in a run's link statistics. A stall of the run shortens both sides alike. A robot
that does not move at all reads 0 (2 mm of pose noise against the 0.29 m commanded in a window: < 0.02).
"""

from __future__ import annotations

import math
from collections import deque

WINDOW = 1.0  # s of wall time compared
MIN_COMMANDED = 0.05  # m commanded in the window before anything is judged (a platoon at 0.35 m/s: 0.35 m)
MIN_RATIO = 0.25  # moved / commanded below this: the robot does not answer


class MotionWatch:
    """Feed it each step's command and the newest measured position; ``problem`` says if the robot is not moving."""

    def __init__(self, window: float = WINDOW, min_commanded: float = MIN_COMMANDED, min_ratio: float = MIN_RATIO) -> None:
        self.window, self.min_commanded, self.min_ratio = window, min_commanded, min_ratio
        self._history: deque[tuple[float, float, float, float]] = deque()  # (time, commanded so far, x, y)
        self._commanded = 0.0
        self._speed = 0.0  # the forward speed of the command in effect
        self._validity = 0.0
        self.ratio_min = math.inf  # the lowest moved / commanded over a judged window (for the link statistics)

    def observe(self, now: float, x: float, y: float, speed: float, validity: float) -> str | None:
        """At ``now`` the robot measured at (x, y), and a command of forward ``speed`` valid for ``validity``
        s is sent: the problem if over the last window it moved less than ``min_ratio`` of what it was asked."""
        if self._history:
            elapsed = now - self._history[-1][0]
            self._commanded += abs(self._speed) * min(max(elapsed, 0.0), self._validity)
        self._speed, self._validity = speed, validity
        self._history.append((now, self._commanded, x, y))
        while len(self._history) > 2 and now - self._history[1][0] >= self.window:
            self._history.popleft()
        start, commanded_then, x0, y0 = self._history[0]
        commanded = self._commanded - commanded_then
        if now - start < self.window or commanded < self.min_commanded:
            return None
        moved = math.hypot(x - x0, y - y0)
        ratio = moved / commanded
        self.ratio_min = min(self.ratio_min, ratio)
        if ratio >= self.min_ratio:
            return None
        return (f"commanded to move {commanded:.3f} m in the last {now - start:.2f} s, its poses moved {moved:.3f} m "
                f"(less than {self.min_ratio:.0%}): it does not answer this run's commands")
