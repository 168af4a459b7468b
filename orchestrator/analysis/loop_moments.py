"""The paper law's own loop through its links, beacon by beacon: does it settle, on average and in every run?

Under the paper's law vehicle i sets its speed from its follower's gap, and the follower computes that gap
from vehicle i's position as *its* backward link shows it: vehicle i's own position comes back to it
through two links (backward, then forward). The sampled-data cascade (``sampled_chain``) gives the
periodic steady state of the string, the mean over the losses, and says nothing of whether that steady
state is reached. This module does, for the semantics the cascade models (a line, kinematic vehicles, the
Jacobi master, beacon periods that are multiples of the step, ``chain_model.ChainModel.missing``):

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
from typing import Callable

import numpy as np

from orchestrator.analysis.chain_model import ChainModel, Timing
from orchestrator.analysis.sampled_chain import step_maps

MOST_PATTERNS = 4096  # delivery patterns per period enumerated (2 ** beacons reaching a receiver per period)
# The second moment's matrix is state^2 square: 45 (2025 x 2025) takes 1.3 s on a 2-core machine. That is 7
# beacons in flight per link, e.g. 0.7 s delays at 10 Hz beacons; beyond, the mean alone is computed.
DENSE_STATE = 45


@dataclass(frozen=True)
class PaperLoop:
    """The paper law's loop of one vehicle through its follower's two links (module docstring): the law's
    ``k_v`` and ``c`` = V_c/d* (its gap gain over k_v), the step ``h`` (s), the coupling, and the links, each
    a ``Timing`` (lag and beacon period in steps, loss): ``to_follower``, the follower's backward link,
    through which it sees this vehicle, and ``from_follower``, its forward link, through which this
    vehicle hears the follower's gap."""

    k_v: float
    c: float
    h: float
    extrapolate: bool
    to_follower: Timing
    from_follower: Timing

    @property
    def period(self) -> int:
        """The lifting period in steps: both links' beacons repeat after it."""
        return math.lcm(self.to_follower.every, self.from_follower.every)


@dataclass(frozen=True)
class LoopRadii:
    """The loop's spectral radii per lifting period of ``period`` steps of ``step`` s: of the mean's map and
    of the second moment's (``mean_square``; None where not computed, ``reason`` says why)."""

    mean: float
    mean_square: float | None
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
    def mean_square_stable(self) -> bool | None:
        return None if self.mean_square is None else self.mean_square < 1.0


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

    def __init__(self, loop: PaperLoop) -> None:
        out, back = loop.to_follower, loop.from_follower
        self.beacons_pending = [b for b in range(-out.lag, 0) if b % out.every == 0]
        self.gaps_pending = [b for b in range(-back.lag, 0) if b % back.every == 0]
        self.size = 2 + 3 * len(self.beacons_pending) + 3 + 2 * len(self.gaps_pending) + 2

    def unpack(self, state: np.ndarray):
        rows = iter(state)
        s = [next(rows), next(rows)]
        beacons = {b: [next(rows) for _ in range(3)] for b in self.beacons_pending}
        seen = [next(rows) for _ in range(3)]
        gaps = {b: [next(rows) for _ in range(2)] for b in self.gaps_pending}
        heard = [next(rows) for _ in range(2)]
        return s, beacons, seen, gaps, heard


TO_FOLLOWER, FROM_FOLLOWER = "to follower", "from follower"  # a delivery: (link, step of the period)


def period_maps(loop: PaperLoop) -> list[tuple[float, np.ndarray]]:
    """(probability, Phi) for every pattern of deliveries over one lifting period of ``loop``: the loop's
    state at the next period's start from this one's. Raises ValueError if the period holds more than
    ``MOST_PATTERNS`` patterns."""
    links = {TO_FOLLOWER: loop.to_follower, FROM_FOLLOWER: loop.from_follower}
    arrivals = [(name, k) for name, link in links.items() for k in range(loop.period)
                if (k - link.lag) % link.every == 0]
    lossy = [arrival for arrival in arrivals if links[arrival[0]].loss > 0.0]
    if 2 ** len(lossy) > MOST_PATTERNS:
        raise ValueError(f"{len(lossy)} lossy deliveries a period: too many patterns to enumerate")
    layout = _Layout(loop)
    maps = []
    for pattern in itertools.product((True, False), repeat=len(lossy)):
        delivered = dict(zip(lossy, pattern))
        probability = math.prod(1.0 - links[a[0]].loss if ok else links[a[0]].loss for a, ok in delivered.items())
        maps.append((probability, _one_period(loop, layout, lambda arrival: delivered.get(arrival, True))))
    return maps


def _one_period(loop: PaperLoop, layout: _Layout, delivered: Callable[[tuple[str, int]], bool]) -> np.ndarray:
    """Phi for one delivery pattern (``delivered((link, k))``): the loop stepped symbolically (every quantity
    a row over the initial state's unit vectors), in the order the Jacobi master computes it."""
    h, extrapolate, out, back = loop.h, loop.extrapolate, loop.to_follower, loop.from_follower
    flow, gammas = step_maps(np.array([[0.0, 1.0], [0.0, -loop.k_v]]), h)
    gain = -loop.k_v * loop.c  # dV_s/dt's gain on the gap the vehicle hears
    s, beacons, seen, gaps, heard = layout.unpack(np.eye(layout.size))
    zero = np.zeros(layout.size)
    for k in range(loop.period):
        heard_at_end = heard[0] + h * heard[1] if extrapolate else heard[0]  # last step's input at t_k
        if k % out.every == 0:  # the broadcast at t_k: x, speed, rate (state and the inputs of the step before)
            beacons[k] = [s[0], s[1], -loop.k_v * s[1] + gain * heard_at_end]
        if k % back.every == 0:  # the follower's gap at t_k, from its view of the step before moved to t_k
            moved = shift_view(seen, 1, h) if extrapolate else seen
            gaps[k] = [moved[0], moved[1] if extrapolate else zero]
        if (k - out.lag) % out.every == 0 and delivered((TO_FOLLOWER, k)):
            beacon = beacons.pop(k - out.lag)
            seen = shift_view(beacon, out.lag, h) if extrapolate else [beacon[0], zero, zero]
        elif extrapolate:
            seen = shift_view(seen, 1, h)
        if (k - back.lag) % back.every == 0 and delivered((FROM_FOLLOWER, k)):
            gap = gaps.pop(k - back.lag)
            heard = shift_view(gap, back.lag, h) if extrapolate else [gap[0], zero]
        elif extrapolate:
            heard = shift_view(heard, 1, h)
        forcing = [gain * heard[0], gain * heard[1] if extrapolate else zero]
        s = [flow[i, 0] * s[0] + flow[i, 1] * s[1] + gammas[0][i, 1] * forcing[0] + gammas[1][i, 1] * forcing[1]
             for i in range(2)]
    rows = [*s]
    for b in layout.beacons_pending:
        rows += beacons[b + loop.period]
    rows += seen
    for b in layout.gaps_pending:
        rows += gaps[b + loop.period]
    rows += heard
    return np.array(rows)


def _second_moment_radius(maps: list[tuple[float, np.ndarray]]) -> float:
    """The spectral radius of Q -> sum pi Phi Q Phi^T, from the matrix sum pi Phi (x) Phi. (Not by power
    iteration: the loop's slowest mode is an oscillation, a complex pair lambda, conj(lambda), and the
    second moment's map then has lambda^2, |lambda|^2 and conj(lambda)^2, all of one modulus.)"""
    operator = sum(p * np.kron(phi, phi) for p, phi in maps)
    return float(np.abs(np.linalg.eigvals(operator)).max())


def paper_loop(chain: ChainModel, vehicle: int) -> PaperLoop | None:
    """``vehicle``'s loop through its follower's links; None where no link is inside it (acc, cacc, the paper
    law's last vehicle)."""
    v = chain.vehicle(vehicle)
    if v.law != "paper" or v.last:
        return None
    return PaperLoop(v.k_v, v.c, chain.step, v.extrapolate, to_follower=v.gap_link, from_follower=v.comm)


def loop_radii(chain: ChainModel, vehicle: int, mean_square: bool = True) -> LoopRadii | None:
    """The radii per lifting period of ``vehicle``'s loop through its follower's links, of the mean over the
    losses and (``mean_square``) of the second moment; None where no link is inside the loop (``paper_loop``).
    For chains the lifting models (``ChainModel.missing`` None)."""
    loop = paper_loop(chain, vehicle)
    if loop is None:
        return None
    if loop.to_follower.bursty or loop.from_follower.bursty:
        return LoopRadii(math.nan, None, loop.period, loop.h, "burst losses (a beacon's loss depends on the one before)")
    try:
        return _loop_radii(loop, mean_square)
    except ValueError as error:
        return LoopRadii(math.nan, None, loop.period, loop.h, str(error))


@functools.lru_cache(maxsize=256)
def _loop_radii(loop: PaperLoop, mean_square: bool) -> LoopRadii:
    """``loop_radii`` of one loop, remembered: a map's runs repeat their grid's loops."""
    maps = period_maps(loop)
    mean = float(np.abs(np.linalg.eigvals(sum(p * phi for p, phi in maps))).max())
    if len(maps) == 1:  # no losses: the second moment is the mean's square
        return LoopRadii(mean, mean * mean, loop.period, loop.h)
    size = len(maps[0][1])
    if size > DENSE_STATE:
        return LoopRadii(mean, None, loop.period, loop.h, f"a loop state of {size} (more than {DENSE_STATE}: the "
                         "links hold too many beacons in flight for the second moment's matrix)")
    return LoopRadii(mean, _second_moment_radius(maps) if mean_square else None, loop.period, loop.h)


def loop_lines(chain: ChainModel, vehicle: int) -> list[str]:
    """`platoon analyze`'s lines on the paper law's loop through its links (none for acc and cacc)."""
    radii = loop_radii(chain, vehicle)
    if radii is None:
        return []
    head = "  the vehicle's own loop through its follower's links (exact, beacon by beacon):"
    if math.isnan(radii.mean):
        return [f"{head} not computed for {radii.reason}"]
    every = f"{radii.period * radii.step:g} s"
    if not radii.mean_stable:
        return [f"{head} GROWS by {radii.mean:.6f} per {every} ({radii.per_second(radii.mean):+.4g} 1/s): the "
                f"platoon itself is unstable and has no steady state; the cascade's gains are moot"]
    mean = f"its mean decays by {radii.mean:.6f} per {every} ({radii.per_second(radii.mean):+.4g} 1/s)"
    if radii.mean_square is None:
        return [f"{head} {mean}; mean square not computed for {radii.reason}"]
    rate = radii.per_second(radii.mean_square, 0.5)
    if radii.mean_square_stable:
        return [f"{head} {mean}, its rms over the losses {rate:+.4g} 1/s (mean square): it settles"]
    return [f"{head} {mean}, but its rms over the losses GROWS at {rate:+.4g} 1/s (mean square): long runs of "
            "lost beacons make rare excursions that grow without bound on average over runs (a single run may "
            "still settle: it follows the almost-sure rate, which is not computed)"]
