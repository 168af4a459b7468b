"""Where a robot's wheels take it under the wheel commands a run sent: the path ``platoon calibrate`` fits.

The robot's physics is ``fmus.model.dynamics.M3piDynamics.drive``: each wheel heads for its target
(``wheel_target``: dead-band, gain, limit) with the first-order motor lag, and the body moves as a
unicycle. Between two commands the target is constant, so the lag's solution is exact,
v(t) = target + (v0 - target) exp(-(t - t0)/T), and so is the heading, the integral of (v_r - v_l)/track.
Only the position, the integral of v (cos heading, sin heading), is a quadrature (Simpson's rule on
the poses' own times and the midpoints between them, exact to micrometres at 200 poses a second). That
makes one path of a two-minute trace a few tens of milliseconds of numpy, where stepping ``drive`` with
RK4 would take seconds; tests/test_calibrate.py holds this path to ``integrate(drive)``.

The commands reach the robot as the m3pi emulator (bridge/emulator.py) applies them: each
``command_latency`` after it was sent; a command whose deadline passed on the way is never applied (a
stop always is); a command holds until the next one or its own deadline, whichever comes first, after
which the wheels head for zero.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from fmus.model.dynamics import M3piDynamics


@dataclass(frozen=True)
class Commands:
    """The wheel commands a run sent to one robot: send times and deadlines (s, one clock with the poses'), and
    when the robot's poses say it applied each: after ``earliest`` (a pose taken then did not echo it yet) and
    by ``latest`` (the first pose echoing it or a later one). Without echoes (a motion capture of its own:
    command number 0 in every pose) both are unbounded."""

    sent: np.ndarray
    deadline: np.ndarray
    left: np.ndarray
    right: np.ndarray
    earliest: np.ndarray | None = None
    latest: np.ndarray | None = None


@dataclass(frozen=True)
class WheelHistory:
    """The wheels between events: from ``times[j]`` on, each heads for its target starting from its speed."""

    times: np.ndarray
    target_right: np.ndarray
    target_left: np.ndarray
    right: np.ndarray  # wheel speed at times[j]
    left: np.ndarray
    turned: np.ndarray  # integral of (v_r - v_l) from times[0] to times[j], m (divide by the track: rad)
    time_constant: float


def command_events(commands: Commands, latency: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(times, left, right): the command each wheel has from each time on, as the robot applies them: ``latency``
    after it was sent, or as early or late as the poses' echoes say it was at the latest or earliest (a command
    held up on the way, by a stalled machine, is not the radio's latency)."""
    applied = commands.sent + latency
    if commands.earliest is not None and commands.latest is not None:
        applied = np.minimum(np.maximum(applied, commands.earliest), commands.latest)
    stop = (commands.left == 0.0) & (commands.right == 0.0)
    keep = stop | (commands.deadline > applied)
    applied, deadline = applied[keep], np.where(stop[keep], np.inf, commands.deadline[keep])
    left, right = commands.left[keep], commands.right[keep]
    following = np.append(applied[1:], np.inf)
    lapsed = deadline < following  # the deadline passed before the next command: the wheels head for zero
    times = np.concatenate([applied, deadline[lapsed]])
    order = np.argsort(times, kind="stable")
    zeros = np.zeros(int(lapsed.sum()))
    return times[order], np.concatenate([left, zeros])[order], np.concatenate([right, zeros])[order]


def wheel_targets(dynamics: M3piDynamics, commands: np.ndarray, gain: float) -> np.ndarray:
    """``M3piDynamics.wheel_target`` of every command at once: no speed inside the dead-band, else the gain times
    the command within the limit. Its numpy twin, held to it bit for bit by tests/test_calibrate.py (a
    two-minute trace asks this of 24 000 commands hundreds of times)."""
    limit = dynamics.wheel_speed_max
    return np.where(np.abs(commands) < dynamics.wheel_deadband, 0.0,
                    np.minimum(np.maximum(gain * commands, -limit), limit))


def lagged(times: np.ndarray, targets: np.ndarray, lag: float) -> np.ndarray:
    """A wheel's speed at each event, from rest at the first, heading for ``targets[j]`` from ``times[j]`` with
    the first-order lag: v[j+1] = target[j] + (v[j] - target[j]) exp(-(times[j+1] - times[j])/lag).

    Written as w = v exp(t/lag), which only accumulates (w[j+1] = w[j] + target[j] (exp(t[j+1]/lag) -
    exp(t[j]/lag))), so numpy's cumsum does it; in blocks of at most 300 lags, within which the exponentials
    stay far from overflow."""
    speeds = np.zeros(len(times))
    start = 0
    while start < len(times) - 1:
        end = min(max(int(np.searchsorted(times, times[start] + 300.0 * lag, side="right")), start + 2), len(times))
        since = times[start:end] - times[start]
        grow = np.exp(since[1:] / lag)
        gained = targets[start:end - 1] * -np.expm1(-np.diff(since) / lag) * grow
        speeds[start + 1:end] = (speeds[start] + np.cumsum(gained)) / grow
        start = end - 1
    return speeds


def wheel_history(dynamics: M3piDynamics, commands: Commands, latency: float) -> WheelHistory:
    """Each wheel's speed at every command event, from rest before the first (exact first-order lag)."""
    times, left, right = command_events(commands, latency)
    target_right = wheel_targets(dynamics, right, dynamics.wheel_gain_right)
    target_left = wheel_targets(dynamics, left, dynamics.wheel_gain_left)
    lag = dynamics.motor_time_constant
    right_speed, left_speed = lagged(times, target_right, lag), lagged(times, target_left, lag)
    span = np.diff(times)
    gone = 1.0 - np.exp(-span / lag)
    between = ((target_right - target_left)[:-1] * span
               + ((right_speed - target_right) - (left_speed - target_left))[:-1] * lag * gone)
    turned = np.concatenate([[0.0], np.cumsum(between)])
    return WheelHistory(times, target_right, target_left, right_speed, left_speed, turned, lag)


def wheels_at(history: WheelHistory, t: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(v_right, v_left, turned) at times ``t``: the exact lag solution from the last event before each."""
    index = np.clip(np.searchsorted(history.times, t, side="right") - 1, 0, len(history.times) - 1)
    since = np.maximum(t - history.times[index], 0.0)
    lag = history.time_constant
    fade = np.exp(-since / lag)
    tr, tl = history.target_right[index], history.target_left[index]
    offset_right, offset_left = history.right[index] - tr, history.left[index] - tl
    before = t < history.times[0]  # at rest before the first command
    right = np.where(before, 0.0, tr + offset_right * fade)
    left = np.where(before, 0.0, tl + offset_left * fade)
    turned = history.turned[index] + (tr - tl) * since + (offset_right - offset_left) * lag * (1.0 - fade)
    return right, left, np.where(before, 0.0, turned)


@dataclass(frozen=True)
class DeadReckoned:
    """The model's path at the pose times, from the origin heading along x at ``t[0]`` (a rigid motion away
    from the recorded one), with its wheel speeds and heading."""

    t: np.ndarray
    x: np.ndarray
    y: np.ndarray
    heading: np.ndarray
    right: np.ndarray
    left: np.ndarray


def dead_reckon(dynamics: M3piDynamics, commands: Commands, latency: float, t: np.ndarray) -> DeadReckoned:
    """The unicycle's path at the increasing times ``t`` under ``commands`` (Simpson between neighbours)."""
    history = wheel_history(dynamics, commands, latency)
    middle = 0.5 * (t[1:] + t[:-1])
    right, left, turned = wheels_at(history, t)
    mid_right, mid_left, mid_turned = wheels_at(history, middle)
    heading, mid_heading = turned / dynamics.track, mid_turned / dynamics.track
    speed, mid_speed = 0.5 * (right + left), 0.5 * (mid_right + mid_left)
    span = np.diff(t) / 6.0
    along_x, along_y = speed * np.cos(heading), speed * np.sin(heading)
    steps_x = (along_x[:-1] + 4.0 * mid_speed * np.cos(mid_heading) + along_x[1:]) * span
    steps_y = (along_y[:-1] + 4.0 * mid_speed * np.sin(mid_heading) + along_y[1:]) * span
    x = np.concatenate([[0.0], np.cumsum(steps_x)])
    y = np.concatenate([[0.0], np.cumsum(steps_y)])
    return DeadReckoned(t, x, y, heading, right, left)


def rigid_fit(model_x: np.ndarray, model_y: np.ndarray, x: np.ndarray, y: np.ndarray,
              segment: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per segment (labels 0..n-1), the rotation and translation that put the model's path best on the
    recorded one (least squares, closed form); returns the moved model path and each point's rotation."""
    count = np.bincount(segment).astype(float)

    def mean(values: np.ndarray) -> np.ndarray:
        return (np.bincount(segment, values) / count)[segment]

    ax, ay = model_x - mean(model_x), model_y - mean(model_y)
    bx, by = x - mean(x), y - mean(y)
    angle = np.arctan2(np.bincount(segment, ax * by - ay * bx), np.bincount(segment, ax * bx + ay * by))[segment]
    c, s = np.cos(angle), np.sin(angle)
    return c * ax - s * ay + mean(x), s * ax + c * ay + mean(y), angle


def segments(t: np.ndarray, length: float) -> np.ndarray:
    """Labels 0, 1, ... cutting times ``t`` (from ``t[0]``) into pieces ``length`` s long (the last takes the rest)."""
    label = np.floor((t - t[0]) / length).astype(int)
    last = max(int(math.floor((t[-1] - t[0]) / length)) - 1, 0)
    return np.minimum(label, last)
