"""Does the robot answer its commands? A run that drives nothing must not say "completed".

A robot whose poses keep arriving but do not move while the run commands it to (the command topic
misspelled behind a DDS bridge, a base that listens to another topic, a robot whose driver ignores
this host) would otherwise let the run end with exit 0. ``MotionWatch`` compares, over the last
``WINDOW`` seconds of the poses' own time stamps, the way the run commanded over that time (the
commanded forward speed, each command counted for at most its validity, so that a stall of the run,
during which the robot rightly stops at its deadline, is not blamed on the robot) with the way its
measured poses moved (straight-line distance between the first and the last pose of the window).

Only new poses are judged: while no pose arrives (a motion capture that lost the robot for a moment, a
stalled link), the newest pose says nothing of how the robot moves since, so the watch waits, and the
silence itself is ``pose_timeout``'s to judge (up to 5 s). When poses come back, the window runs from a
pose at least ``WINDOW`` s older by its stamp, so it spans the silence and the robot's motion through it.

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
from bisect import bisect_right
from collections import deque

WINDOW = 1.0  # s of pose time compared
MIN_COMMANDED = 0.05  # m commanded in the window before anything is judged (a platoon at 0.35 m/s: 0.35 m)
MIN_RATIO = 0.25  # moved / commanded below this: the robot does not answer


class MotionWatch:
    """Feed it each step's command and the newest measured pose; ``problem`` says if the robot is not moving."""

    def __init__(self, window: float = WINDOW, min_commanded: float = MIN_COMMANDED, min_ratio: float = MIN_RATIO) -> None:
        self.window, self.min_commanded, self.min_ratio = window, min_commanded, min_ratio
        # each command: when it was sent, the distance commanded before it, its |forward speed| and validity
        self._sent: list[float] = []
        self._commands: list[tuple[float, float, float]] = []
        self._poses: deque[tuple[float, float, float]] = deque()  # (stamp, x, y), one per new pose
        self.ratio_min = math.inf  # the lowest moved / commanded over a judged window (for the link statistics)

    def commanded_until(self, t: float) -> float:
        """The distance commanded from the first command kept until time ``t``."""
        index = bisect_right(self._sent, t) - 1
        if index < 0:
            return self._commands[0][0] if self._commands else 0.0
        before, speed, validity = self._commands[index]
        return before + speed * min(t - self._sent[index], validity)

    def observe(self, now: float, stamp: float, x: float, y: float, speed: float, validity: float) -> str | None:
        """At ``now`` a command of forward ``speed`` valid for ``validity`` s is sent, and the newest pose is
        (x, y) taken at ``stamp``: the problem if, over the last window of new poses, the robot moved less than
        ``min_ratio`` of what it was asked; None while no new pose arrived."""
        before = self.commanded_until(now) if self._commands else 0.0
        self._sent.append(now)
        self._commands.append((before, abs(speed), validity))
        if self._poses and stamp <= self._poses[-1][0]:
            return None  # no new pose: nothing to judge, the silence is pose_timeout's
        self._poses.append((stamp, x, y))
        while len(self._poses) > 2 and stamp - self._poses[1][0] >= self.window:
            self._poses.popleft()
        start, x0, y0 = self._poses[0]
        self._forget_before(start)
        commanded = self.commanded_until(stamp) - self.commanded_until(start)
        if stamp - start < self.window or commanded < self.min_commanded:
            return None
        moved = math.hypot(x - x0, y - y0)
        ratio = moved / commanded
        self.ratio_min = min(self.ratio_min, ratio)
        if ratio >= self.min_ratio:
            return None
        return (f"commanded to move {commanded:.3f} m in the last {stamp - start:.2f} s, its poses moved {moved:.3f} m "
                f"(less than {self.min_ratio:.0%}): it does not answer this run's commands")

    def _forget_before(self, t: float) -> None:
        """Drop the commands no window will need: all sent before the last one sent at or before ``t``."""
        index = bisect_right(self._sent, t) - 1
        if index > 0:
            del self._sent[:index], self._commands[:index]
