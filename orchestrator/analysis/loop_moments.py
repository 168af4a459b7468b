"""The paper law's own loop through its links, beacon by beacon: does it settle, on average and in every run?

Under the paper's law vehicle i sets its speed from its follower's gap, and the follower computes that gap
from vehicle i's position as *its* backward link shows it: vehicle i's own position comes back to it
through two links (backward, then forward). The sampled-data cascade (``sampled_chain``) gives the
periodic steady state of the string, the mean over the losses, and says nothing of whether that steady
state is reached. This module does, for the semantics the cascade models (a line, kinematic vehicles, the
Jacobi master, beacon periods that are multiples of the step, ``sampled_chain.exact_applies``):

- the loop is stepped exactly over one lifting period of P steps (``step_maps``), the follower's own
  motion left out (it is an input to vehicle i's loop, driven from behind), with every beacon that reaches
  a receiver in that period either delivered or lost. That gives a linear map Phi(delta) of the loop's
  state (the vehicle's x and V_s, the beacons in flight, the views in use) for each pattern delta of
  deliveries, with probability pi(delta) (independent losses: every beacon of every link its own draw);
- the **mean** over the losses evolves by E[Phi] = sum pi Phi: its spectral radius below 1 is the
  loop's stability for the mean (what the cascade's steady state assumes);
- the **second moment** E[z z^T] evolves by Q -> sum pi Phi Q Phi^T, i.e. by the matrix
  sum pi Phi (x) Phi on vec(Q) (a Markov jump linear system with independent jumps, Costa, Fragoso and
  Marques, *Discrete-Time Markov Jump Linear Systems*, 2005, ch. 3): its spectral radius below 1 is
  mean-square stability. Above 1 a single run's deviations grow without bound even though their mean
  decays: long runs of lost beacons make rare excursions large enough to outweigh the rest. A single run
  may still settle (it follows the almost-sure rate, the top Lyapunov exponent, at most the mean
  square's: a study of 2 vehicles, 0.6 s links and 90 % loss has rms +0.092 1/s and four seeds that
  decay), so the mean square is a bound on how reliably runs settle, not the fate of each.

In the loop's state a view in use is its extrapolation polynomial at the current step (value, rate,
second rate): moving it one step on is a fixed linear map, so a message's growing age needs no state of
its own, and a delivery replaces the polynomial by the new beacon's at its age. Held coupling keeps the
value only. acc and cacc have no link inside a vehicle's loop (the sensor is a plain connection and the
message comes from the vehicle ahead): their loops are the continuous ones of ``Vehicle.loop``, stable
for positive gains, and losses only make the input noisy.

Pure computation (numpy), no I/O.
"""

from __future__ import annotations

import functools
import itertools
import math
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from orchestrator.analysis.sampled_chain import step_maps, timing_of, vehicle_of

if TYPE_CHECKING:
    from orchestrator.scenario.config import Config

MOST_PATTERNS = 4096  # delivery patterns per period enumerated (2 ** beacons reaching a receiver per period)
# The second moment's matrix is state^2 square: 45 (2025 x 2025) takes 1.3 s on a 2-core machine. That is 7
# beacons in flight per link, e.g. 0.7 s delays at 10 Hz beacons; beyond, the mean alone is computed.
DENSE_STATE = 45


@dataclass(frozen=True)
class LoopLink:
    """A link inside the loop: its receiver takes beacon b (sent at a multiple of ``every`` steps) from
    step b + ``lag`` on, unless it is lost (probability ``loss``, independently per beacon)."""

    lag: int
    every: int
    loss: float


@dataclass(frozen=True)
class LoopGrowth:
    """Per lifting period of ``period`` steps of ``step`` s: the spectral radius of the mean's map and of the
    second moment's (None where not computed, ``reason`` says why)."""

    mean: float
    square: float | None
    period: int
    step: float
    reason: str = ""

    def per_second(self, radius: float, power: float = 1.0) -> float:
        """A radius per period as a growth rate (1/s) of an amplitude (``power`` 0.5 for a second moment)."""
        return power * math.log(max(radius, 1e-300)) / (self.period * self.step)

    @property
    def mean_stable(self) -> bool:
        return self.mean < 1.0

    @property
    def square_stable(self) -> bool | None:
        return None if self.square is None else self.square < 1.0


def shift_view(view: list[np.ndarray], steps: int, h: float) -> list[np.ndarray]:
    """An extrapolation polynomial (value, rate, second rate, as rows over the loop's initial state) moved
    ``steps`` steps on: value + D rate + D^2/2 second rate, and so on, D = steps h."""
    d = steps * h
    if len(view) == 3:
        return [view[0] + d * view[1] + 0.5 * d * d * view[2], view[1] + d * view[2], view[2]]
    return [view[0] + d * view[1], view[1]]


class _Layout:
    """Where each part of the loop's state sits at a period's start: the vehicle's (x, V_s), the beacons of
    its broadcast (x, speed, rate) still in flight to the follower, the follower's view of it, the gap
    messages (gap, rate) still in flight back, and the vehicle's view of them."""

    def __init__(self, q: LoopLink, f: LoopLink) -> None:
        self.q_pending = [b for b in range(-q.lag, 0) if b % q.every == 0]
        self.f_pending = [b for b in range(-f.lag, 0) if b % f.every == 0]
        self.size = 2 + 3 * len(self.q_pending) + 3 + 2 * len(self.f_pending) + 2

    def unpack(self, state: np.ndarray):
        rows = iter(state)
        s = [next(rows), next(rows)]
        beacons = {b: [next(rows) for _ in range(3)] for b in self.q_pending}
        seen = [next(rows) for _ in range(3)]
        gaps = {b: [next(rows) for _ in range(2)] for b in self.f_pending}
        heard = [next(rows) for _ in range(2)]
        return s, beacons, seen, gaps, heard


def period_maps(k_v: float, c: float, h: float, extrapolate: bool, q: LoopLink, f: LoopLink,
                period: int) -> list[tuple[float, np.ndarray]]:
    """(probability, Phi) for every pattern of deliveries over one period of ``period`` steps (a multiple
    of both links' beacon periods): the loop's state at the next period's start from this one's.

    ``q``: the follower's backward link (it sees this vehicle through it), ``f``: the follower's forward
    link (this vehicle hears the follower's gap through it); ``c`` = V_c/d*, the law's gap gain over k_v.
    Raises ValueError if the period holds more than ``MOST_PATTERNS`` patterns."""
    layout = _Layout(q, f)
    loss = {"q": q.loss, "f": f.loss}
    arrivals = [("q", k) for k in range(period) if (k - q.lag) % q.every == 0]
    arrivals += [("f", k) for k in range(period) if (k - f.lag) % f.every == 0]
    lossy = [arrival for arrival in arrivals if loss[arrival[0]] > 0.0]
    if 2 ** len(lossy) > MOST_PATTERNS:
        raise ValueError(f"{len(lossy)} lossy deliveries a period: too many patterns to enumerate")
    maps = []
    for pattern in itertools.product((True, False), repeat=len(lossy)):
        delivered = dict(zip(lossy, pattern))
        probability = math.prod(1.0 - loss[a[0]] if ok else loss[a[0]] for a, ok in delivered.items())
        maps.append((probability, _one_period(k_v, c, h, extrapolate, q, f, period, layout,
                                              lambda arrival: delivered.get(arrival, True))))
    return maps


def _one_period(k_v, c, h, extrapolate, q, f, period, layout, delivered) -> np.ndarray:
    """Phi for one delivery pattern: the loop stepped symbolically (every quantity a row over the initial
    state's unit vectors), in the order the Jacobi master computes it."""
    flow, gammas = step_maps(np.array([[0.0, 1.0], [0.0, -k_v]]), h)
    gain = -k_v * c  # dV_s/dt's gain on the gap the vehicle hears
    s, beacons, seen, gaps, heard = layout.unpack(np.eye(layout.size))
    zero = np.zeros(layout.size)
    for k in range(period):
        heard_at_end = heard[0] + h * heard[1] if extrapolate else heard[0]  # last step's input at t_k
        if k % q.every == 0:  # the broadcast at t_k: x, speed, rate (state and the inputs of the step before)
            beacons[k] = [s[0], s[1], -k_v * s[1] + gain * heard_at_end]
        if k % f.every == 0:  # the follower's gap at t_k, from its view of the step before moved to t_k
            moved = shift_view(seen, 1, h) if extrapolate else seen
            gaps[k] = [moved[0], moved[1] if extrapolate else zero]
        if (k - q.lag) % q.every == 0 and delivered(("q", k)):
            beacon = beacons.pop(k - q.lag)
            seen = shift_view(beacon, q.lag, h) if extrapolate else [beacon[0], zero, zero]
        elif extrapolate:
            seen = shift_view(seen, 1, h)
        if (k - f.lag) % f.every == 0 and delivered(("f", k)):
            gap = gaps.pop(k - f.lag)
            heard = shift_view(gap, f.lag, h) if extrapolate else [gap[0], zero]
        elif extrapolate:
            heard = shift_view(heard, 1, h)
        forcing = [gain * heard[0], gain * heard[1] if extrapolate else zero]
        s = [flow[i, 0] * s[0] + flow[i, 1] * s[1] + gammas[0][i, 1] * forcing[0] + gammas[1][i, 1] * forcing[1]
             for i in range(2)]
    rows = [*s]
    for b in layout.q_pending:
        rows += beacons[b + period]
    rows += seen
    for b in layout.f_pending:
        rows += gaps[b + period]
    rows += heard
    return np.array(rows)


def _second_moment_radius(maps: list[tuple[float, np.ndarray]]) -> float:
    """The spectral radius of Q -> sum pi Phi Q Phi^T, from the matrix sum pi Phi (x) Phi. (Not by power
    iteration: the loop's slowest mode is an oscillation, a complex pair lambda, conj(lambda), and the
    second moment's map then has lambda^2, |lambda|^2 and conj(lambda)^2, all of one modulus.)"""
    operator = sum(p * np.kron(phi, phi) for p, phi in maps)
    return float(np.abs(np.linalg.eigvals(operator)).max())


def loop_growth(config: "Config", vehicle: int, square: bool = True) -> LoopGrowth | None:
    """The growth per lifting period of ``vehicle``'s loop through its follower's links, for the mean over
    the losses and (``square``) for the second moment; None where no link is inside the loop (acc, cacc,
    the paper law's last vehicle). For configs the lifting models (``sampled_chain.exact_applies``)."""
    v = vehicle_of(config, vehicle)
    if v.law != "paper" or v.last:
        return None
    step = config.simulation.step
    directions = ("backward", "forward")  # the follower's: it sees this vehicle, this vehicle hears its gap
    links = [config.resolve_link(d, vehicle + 1) for d in directions]
    timings = [timing_of(config, d, vehicle + 1) for d in directions]
    q, f = (LoopLink(timing.lag, timing.every, 0.0 if link.perfect else link.loss)
            for timing, link in zip(timings, links))
    period = math.lcm(q.every, f.every)
    if any(not link.perfect and link.loss > 0.0 and link.burst > 1.0 for link in links):
        return LoopGrowth(math.nan, None, period, step, "burst losses (a beacon's loss depends on the one before)")
    try:
        return _growth(v.k_v, v.c, step, v.extrapolate, q, f, period, square)
    except ValueError as error:
        return LoopGrowth(math.nan, None, period, step, str(error))


@functools.lru_cache(maxsize=256)
def _growth(k_v: float, c: float, step: float, extrapolate: bool, q: LoopLink, f: LoopLink, period: int,
            square: bool) -> LoopGrowth:
    """``loop_growth`` of one loop, remembered: a map's runs repeat their grid's loops."""
    maps = period_maps(k_v, c, step, extrapolate, q, f, period)
    mean = float(np.abs(np.linalg.eigvals(sum(p * phi for p, phi in maps))).max())
    if len(maps) == 1:  # no losses: the second moment is the mean's square
        return LoopGrowth(mean, mean * mean, period, step)
    size = len(maps[0][1])
    if size > DENSE_STATE:
        return LoopGrowth(mean, None, period, step, f"a loop state of {size} (more than {DENSE_STATE}: the links "
                          "hold too many beacons in flight for the second moment's matrix)")
    return LoopGrowth(mean, _second_moment_radius(maps) if square else None, period, step)


def loop_lines(config: "Config", vehicle: int) -> list[str]:
    """`platoon analyze`'s lines on the paper law's loop through its links (none for acc and cacc)."""
    growth = loop_growth(config, vehicle)
    if growth is None:
        return []
    head = "  the vehicle's own loop through its follower's links (exact, beacon by beacon):"
    if math.isnan(growth.mean):
        return [f"{head} not computed for {growth.reason}"]
    every = f"{growth.period * growth.step:g} s"
    if not growth.mean_stable:
        return [f"{head} GROWS by {growth.mean:.6f} per {every} ({growth.per_second(growth.mean):+.4g} 1/s): the "
                f"platoon itself is unstable and has no steady state; the cascade's gains are moot"]
    mean = f"its mean decays by {growth.mean:.6f} per {every} ({growth.per_second(growth.mean):+.4g} 1/s)"
    if growth.square is None:
        return [f"{head} {mean}; mean square not computed for {growth.reason}"]
    rate = growth.per_second(growth.square, 0.5)
    if growth.square_stable:
        return [f"{head} {mean}, its rms over the losses {rate:+.4g} 1/s (mean square): it settles"]
    return [f"{head} {mean}, but its rms over the losses GROWS at {rate:+.4g} 1/s (mean square): long runs of "
            "lost beacons make rare excursions that grow without bound on average over runs (a single run may "
            "still settle: it follows the almost-sure rate, which is not computed)"]
