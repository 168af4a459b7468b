"""The speed chain as the co-simulation runs it: a sampled-data cascade, lifted over the beacon period.

``string_stability.Channel`` averages a link over its sampling phase: exact for one link, not for a
string. Synchronized beacons sample every vehicle at the same instants, so what a vehicle passes on
carries, beside the disturbance's frequency w, its aliases at w + 2 pi m/T, and the next link folds
them back onto w in a phase set by the delay against the beacon grid. This module computes the
periodic steady state exactly instead (the lifting of Öncü, van de Wouw, Heemels, Nijmeijer, "String
stability of interconnected vehicles under communication constraints", IEEE T-ITS 2014, on the
co-simulation's own step grid), for the semantics the FMUs and links run:

- Jacobi master, step h: outputs at t_k are computed from the state at t_k and the inputs of the step
  before; inputs set at t_k are used over [t_k, t_k + h), extrapolated from their sample's output_time
  (coupling "extrapolate": positions to order 2, speeds and gaps to order 1) or held ("hold");
- a Link with delay d and beacon period T = n h hands the receiver, at t_k, the newest beacon (sent at a
  multiple of T) with output_time <= t_k - a0, a0 = max(h, ceil(d/h) h); a lost beacon leaves the older
  one in use (losses: independent or Gilbert-Elliott; the result is the mean over them, a product of
  means since every link draws its own stream); a perfect link or the sensor is a plain connection, a0 = 0;
- a speed push is the disturbance's value at t_k held over the step (docs/model.md, section 7).

Each vehicle is linear on a straight line (kinematic: position x and loop speed V_s, deviations from the
steady state). A vehicle's *broadcast*, the (x, speed, speed_rate) it outputs at the P instants of one
lifting period, is a linear function of its sender's broadcast (the vehicle ahead under acc and cacc,
the one behind under the paper's law) and of its own push: b_i = T(w) b_(i-1) + U(w) p_i. Values
outside the period follow from the steady state's phase: x(t_k + P h) = e^{j w P h} x(t_k). The
spectral radius of T(w) is the growth per link far down a long string; the cascade from the config's
own pushes is what a run measures, link by link.

Pure computation (numpy), no I/O. The limits: a line, kinematic vehicles, the Jacobi master, no
jitter, beacon periods that are whole multiples of the step; ``chain_model.ChainModel.missing`` says which is
missing. The chain it lifts (vehicles, links, laws) is ``chain_model``'s.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass, replace
from typing import Callable

import numpy as np

from orchestrator.analysis.chain_model import ChainModel, Timing, Vehicle

KINDS = ("x", "speed", "rate")  # a broadcast's signals: position, speed over ground, speed rate


def _expm(a: np.ndarray) -> np.ndarray:
    """e^a for a small real matrix: Taylor series after scaling to norm <= 1/2, then squaring."""
    squarings = max(0, math.ceil(math.log2(max(np.abs(a).sum(axis=1).max(), 1e-300) / 0.5)))
    scaled = a / 2.0**squarings
    result, term = np.eye(len(a)), np.eye(len(a))
    for n in range(1, 20):
        term = term @ scaled / n
        result = result + term
    for _ in range(squarings):
        result = result @ result
    return result


def step_maps(a: np.ndarray, h: float) -> tuple[np.ndarray, list[np.ndarray]]:
    """(e^{Ah}, [Gamma_q]) with Gamma_q = integral over [0, h] of e^{A(h - tau)} tau^q dtau, q = 0, 1, 2:
    the exact step of s' = A s + sum_q f_q tau^q (Gauss-Legendre, exact to rounding for these smooth
    integrands over one step). Remembered by A and h (read only): a map asks for the same few loops."""
    return _step_maps(a.tobytes(), a.shape, h)


@functools.lru_cache(maxsize=64)
def _step_maps(packed: bytes, shape: tuple[int, ...], h: float) -> tuple[np.ndarray, list[np.ndarray]]:
    a = np.frombuffer(packed).reshape(shape)
    nodes, weights = np.polynomial.legendre.leggauss(12)
    taus = 0.5 * h * (nodes + 1.0)
    flows = [_expm(a * (h - tau)) for tau in taus]
    gammas = [sum(0.5 * h * wt * tau**q * flow for wt, tau, flow in zip(weights, taus, flows)) for q in range(3)]
    flow = _expm(a * h)
    for matrix in (flow, *gammas):
        matrix.flags.writeable = False
    return flow, gammas


class Lifted:
    """Linear functionals over the lifted broadcasts of a sender and a receiver ("self"), per frequency.

    A row is an array (frequencies, 6 P): the sender's (x, speed, rate) at instants 0..P-1, then the
    receiver's. ``place`` puts instant m (any integer) there with its period's phase e^{j w P h floor(m/P)}."""

    def __init__(self, w: np.ndarray, step: float, period: int) -> None:
        self.w, self.h, self.p = np.asarray(w, dtype=float), step, period
        self.zeta = np.exp(1j * self.w * period * step)
        self._memo: dict[tuple, list[np.ndarray]] = {}
        self._powers: dict[int, np.ndarray] = {}  # zeta**turns, by turns (read only)
        self._table: tuple[np.ndarray, np.ndarray] | None = None  # (Re, Im) zeta**turns from _table_low on
        self._table_low = 0

    def zero(self) -> np.ndarray:
        return np.zeros((len(self.w), 6 * self.p), dtype=complex)

    def place(self, owner: str, kind: str, m: int) -> tuple[int, np.ndarray]:
        """The column of (owner, kind) at instant m (any integer) and its phase e^{j w P h floor(m/P)}."""
        turns, instant = divmod(m, self.p)
        if turns not in self._powers:
            self._powers[turns] = self.zeta**turns
        return (0 if owner == "sender" else 3 * self.p) + 3 * instant + KINDS.index(kind), self._powers[turns]

    def samples(self, timing: Timing, k: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(probabilities, beacon instants, their ages at t_k) of the samples a receiver may use over step k,
        as arrays (a lossy link's can be a hundred: every sum over them is one matrix product)."""
        newest = ((k - timing.lag) // timing.every) * timing.every
        beacons = newest - timing.every * np.arange(len(timing.weights))
        return np.array(timing.weights), beacons, (k - beacons) * self.h

    def by_instant(self, timing: Timing, k: int, factors: list["np.ndarray | float"]) -> list[np.ndarray]:
        """Per factor f, sum over the samples of step k of probability x f x e^{j w P h turns}, by the
        sample's instant of the period: arrays (frequencies, P). The sums are polynomials in e^{j w P h}
        whose coefficients (instants x turns) come straight from the samples; evaluating them is one
        small product with a table of powers, so a lossy link's hundred samples cost about one."""
        weights, beacons, _ = self.samples(timing, k)
        turns, instants = np.divmod(beacons, self.p)
        low, high = int(turns.min()), int(turns.max())
        cosines, sines = self._powers_from(low, high)
        sums = []
        for factor in factors:
            coefficients = np.zeros((self.p, high - low + 1))
            np.add.at(coefficients, (instants, turns - low), weights * factor)
            sums.append((coefficients @ cosines + 1j * (coefficients @ sines)).T)
        return sums

    def _powers_from(self, low: int, high: int) -> tuple[np.ndarray, np.ndarray]:
        """(Re, Im) of e^{j w P h t} for t = low .. high, rows of a table kept over the turns asked so far
        (real tables: a real @ real product has BLAS's fast path, a real @ complex one does not)."""
        if self._table is None or low < self._table_low or high >= self._table_low + len(self._table[0]):
            first, last = low, high
            if self._table is not None:
                first, last = min(low, self._table_low), max(high, self._table_low + len(self._table[0]) - 1)
            angles = np.angle(self.zeta)[None, :] * np.arange(first, last + 1)[:, None]
            self._table, self._table_low = (np.cos(angles), np.sin(angles)), first
        cosines, sines = self._table
        rows = slice(low - self._table_low, high - self._table_low + 1)
        return cosines[rows], sines[rows]

    def gather(self, owner: str, timing: Timing, k: int, terms: list[dict[str, "np.ndarray | float"]]) -> list[np.ndarray]:
        """Per dict of ``terms``, the row summing over the samples of step k probability x phase x
        terms[kind] at the sample's (owner, kind) column."""
        first = 0 if owner == "sender" else 3 * self.p
        sums = iter(self.by_instant(timing, k, [factor for row_terms in terms for factor in row_terms.values()]))
        rows = []
        for row_terms in terms:
            row = self.zero()
            for kind in row_terms:
                row[:, first + KINDS.index(kind):first + 3 * self.p:3] += next(sums)
            rows.append(row)
        return rows

    def _shifted(self, build, owner: str, timing: Timing, k: int, extrapolate: bool) -> list[np.ndarray]:
        """``build``'s rows for step k from those of step k mod P: one period later every sample is one
        period later, so the rows are the same times e^{j w P h} (computed once per step of the period)."""
        turns, first = divmod(k, self.p)
        rows = self.remembered((build.__name__, owner, timing, first, extrapolate),
                               lambda: build(owner, timing, first, extrapolate))
        factor = self.zeta[:, None] ** turns
        return [row * factor for row in rows]

    def remembered(self, key: tuple, build: Callable[[], list[np.ndarray]]) -> list[np.ndarray]:
        """``build()``'s rows, computed once per ``key`` for these frequencies (read them, never change them
        in place): every step whose samples are the same beacons uses the same rows."""
        if key not in self._memo:
            self._memo[key] = build()
        return self._memo[key]

    def position(self, owner: str, timing: Timing, k: int, extrapolate: bool) -> list[np.ndarray]:
        """The sender's position as seen over step k, as rows of tau^0, tau^1, tau^2 (along its speed and
        speed rate when extrapolating: x + V (D + tau) + V' (D + tau)^2 / 2, D the sample's age at t_k)."""
        return self._shifted(self._position, owner, timing, k, extrapolate)

    def speed(self, owner: str, timing: Timing, k: int, extrapolate: bool) -> list[np.ndarray]:
        """The sender's speed as seen over step k: rows of tau^0, tau^1 (V + V' (D + tau), or V held)."""
        return self._shifted(self._speed, owner, timing, k, extrapolate)

    def _position(self, owner: str, timing: Timing, k: int, extrapolate: bool) -> list[np.ndarray]:
        # per sample: p (x + age v + age^2/2 a), p (v + age a), p a/2 over unit rows x, v, a
        if not extrapolate:
            return self.gather(owner, timing, k, [{"x": 1.0}]) + [self.zero(), self.zero()]
        age = self.samples(timing, k)[2]
        return self.gather(owner, timing, k, [{"x": 1.0, "speed": age, "rate": 0.5 * age * age},
                                              {"speed": 1.0, "rate": age}, {"rate": 0.5}])

    def _speed(self, owner: str, timing: Timing, k: int, extrapolate: bool) -> list[np.ndarray]:
        # per sample: p (v + age a) (or p v, held), p a over unit rows v, a
        if not extrapolate:
            return self.gather(owner, timing, k, [{"speed": 1.0}]) + [self.zero()]
        age = self.samples(timing, k)[2]
        return self.gather(owner, timing, k, [{"speed": 1.0, "rate": age}, {"rate": 1.0}])


def _gap_message(lift: Lifted, v: Vehicle, k: int) -> list[np.ndarray]:
    """The paper's law: the follower's gap as this vehicle uses it over step k, rows of tau^0, tau^1.

    The follower (the sender) outputs at beacon instant b the distance to this vehicle as *it* sees it,
    through its own backward link (``gap_link``, its inputs of the step before b, extrapolated to t_b),
    minus its own position; and the rate of that. This vehicle receives both through the forward link
    (``comm``) and extrapolates them linearly, or holds them. What is sent at b + m P is what is sent at b
    times e^{j w P h m}: the samples are summed per instant of the period, then times its rows."""
    _, beacons, ages = lift.samples(v.comm, k)
    held, aged = lift.by_instant(v.comm, k, [1.0, ages])
    rows = [lift.zero(), lift.zero()]
    for instant in np.unique(np.mod(beacons, lift.p)):
        gap, rate = _sent_gap(lift, v, int(instant))
        rows[0] += held[:, instant, None] * gap
        if v.extrapolate:
            rows[0] += aged[:, instant, None] * rate
            rows[1] += held[:, instant, None] * rate
    return rows


def _sent_gap(lift: Lifted, v: Vehicle, b: int) -> list[np.ndarray]:
    """The gap and its rate the follower sends at beacon instant b (rows; not to be changed in place).
    Computed once per instant: every step whose sample is beacon b uses the same rows."""
    def build() -> list[np.ndarray]:
        seen = lift.position("self", v.gap_link, b - 1, v.extrapolate)
        seen_speed = lift.speed("self", v.gap_link, b - 1, v.extrapolate)
        h = lift.h
        gap = seen[0] + h * seen[1] + h * h * seen[2]
        rate = seen_speed[0] + h * seen_speed[1]
        (x_column, phase), (speed_column, _) = lift.place("sender", "x", b), lift.place("sender", "speed", b)
        gap[:, x_column] -= phase  # minus the sender's unit rows x and speed at b
        rate[:, speed_column] -= phase
        return [gap, rate]

    return lift.remembered(("sent gap", v.gap_link, b, v.extrapolate), build)


def forcing(lift: Lifted, v: Vehicle) -> dict[int, list[np.ndarray]]:
    """Per step k of the period (and k = -1): the rows of tau^q (q = 0, 1, 2) of what drives dV_s/dt
    besides the vehicle's own state and push."""
    _, gains, _ = v.loop()
    result = {}
    for k in range(-1, lift.p):
        rows = [lift.zero(), lift.zero(), lift.zero()]
        parts = []
        if "sensor" in gains:
            parts.append((gains["sensor"], lift.position("sender", v.sensor, k, v.extrapolate)))
        if "speed" in gains:
            parts.append((gains["speed"], lift.speed("sender", v.comm, k, v.extrapolate)))
        if "gap" in gains:
            parts.append((gains["gap"], _gap_message(lift, v, k)))
        for gain, polynomial in parts:
            for q, row in enumerate(polynomial):
                rows[q] += gain * row
        result[k] = rows
    return result


def receiver_maps(lift: Lifted, v: Vehicle) -> tuple[np.ndarray, np.ndarray]:
    """(T, U): the receiver's broadcast = T @ the sender's broadcast + U * its push (a unit phasor held
    over each step, e^{j w t_k} from t_k), per frequency; shapes (W, 3P, 3P) and (W, 3P).

    Unknowns: the state s(k) = (x, V_s) and the broadcast r(k) = (x, V_s + p(k-1), V_s'(t_k)) at the
    P instants; equations: the exact step s(k+1) = E s(k) + sum_q Gamma_q (0, f_q(k)) + Gamma_0 pi p(k)
    (s(P) = e^{j w P h} s(0)), and the outputs at t_k from s(k) and the inputs of step k - 1."""
    p, w = lift.p, lift.w
    a, _, push = v.loop()
    flow, gammas = step_maps(a, lift.h)
    f = forcing(lift, v)
    size = 5 * p
    m = np.zeros((len(w), size, size), dtype=complex)
    n = np.zeros((len(w), size, 3 * p), dtype=complex)
    rhs = np.zeros((len(w), size), dtype=complex)
    phase = np.exp(1j * np.outer(w, np.arange(-1, p) * lift.h))  # p(k) for k = -1 .. P-1
    for k in range(p):
        here, following = slice(2 * k, 2 * k + 2), slice(2 * ((k + 1) % p), 2 * ((k + 1) % p) + 2)
        m[:, following, following] += np.eye(2) * (lift.zeta[:, None, None] if k + 1 == p else 1.0)
        m[:, following, here] -= flow
        for q in range(3):
            column = gammas[q][:, 1]
            m[:, following, 2 * p:] -= column[None, :, None] * f[k][q][:, None, 3 * p:]
            n[:, following, :] += column[None, :, None] * f[k][q][:, None, :3 * p]
        rhs[:, following] += (gammas[0] @ push)[None, :] * phase[:, k + 1, None]
        x, speed, rate = (2 * p + 3 * k + i for i in range(3))
        m[:, x, x] += 1.0
        m[:, x, 2 * k] -= 1.0
        m[:, speed, speed] += 1.0
        m[:, speed, 2 * k + 1] -= 1.0
        rhs[:, speed] += phase[:, k]
        m[:, rate, rate] += 1.0
        m[:, rate, here] -= a[1]
        before = sum(lift.h**q * f[k - 1][q] for q in range(3))
        m[:, rate, 2 * p:] -= before[:, 3 * p:]
        n[:, rate, :] += before[:, :3 * p]
        rhs[:, rate] += push[1] * phase[:, k]
    solved_n = np.linalg.solve(m, n)
    solved_push = np.linalg.solve(m, rhs[..., None])[..., 0]
    return solved_n[:, 2 * p:, :], solved_push[:, 2 * p:]


def push_phasors(chain: ChainModel, w: float) -> dict[int, complex]:
    """Per vehicle (0: the virtual target), the complex amplitude of its speed pushes at frequency ``w``:
    value sin(w (t - start)) is the imaginary part of value e^{-j w start} e^{j w t}."""
    pushes: dict[int, complex] = {}
    for d in chain.pushes:
        if d.kind == "speed" and abs(d.frequency - w) < 1e-12:
            pushes[d.vehicle] = pushes.get(d.vehicle, 0.0) + d.value * complex(math.cos(w * d.start), -math.sin(w * d.start))
    return pushes


def target_broadcast(lift: Lifted, push: complex) -> np.ndarray:
    """The virtual target's broadcast under acc and cacc (it moves at V_c plus its push): a push p(k) =
    push e^{j w t_k} held over step k gives, at t_k, the speed p(k - 1) (the output follows the inputs of
    the step before), the position x(k) with x(k + 1) = x(k) + h p(k), i.e. h p(k)/(e^{j w h} - 1) in
    the steady state, and no speed rate (a push's rate is not in ``speed_rate``). Shape (3P,)."""
    (w,), h = lift.w, lift.h
    instants = np.arange(lift.p)
    broadcast = np.zeros(3 * lift.p, dtype=complex)
    broadcast[0::3] = push * h * np.exp(1j * w * instants * h) / (np.exp(1j * w * h) - 1.0)
    broadcast[1::3] = push * np.exp(1j * w * (instants - 1) * h)
    return broadcast


def cascade_speeds(chain: ChainModel, order: list[int], w: float, record_every: int) -> list[complex]:
    """The component at ``w`` of each vehicle's speed (along ``order``, the way the law carries a
    disturbance from ``order[0]``), driven by the chain's sinusoidal pushes, as a least-squares fit over
    records every ``record_every`` steps measures it (the mean of the recorded instants' phasors).
    ``order`` may start at 0, the virtual target (acc, cacc: its speed is V_c plus its own pushes)."""
    period = chain.lifting_period(record_every)
    lift = Lifted(np.array([w]), chain.step, period)
    pushes = push_phasors(chain, w)
    broadcast = np.zeros(3 * period, dtype=complex)
    recorded = np.arange(0, period, record_every)
    demodulate = np.exp(-1j * w * recorded * chain.step)
    components = []
    if order and order[0] == 0:
        broadcast = target_broadcast(lift, pushes.get(0, 0.0))
        components.append(complex(np.mean(broadcast[3 * recorded + 1] * demodulate)))
        order = order[1:]
    for index in order:
        t, u = lifted_maps(chain.vehicle(index), lift.w.tobytes(), lift.h, period)
        broadcast = t[0] @ broadcast + u[0] * pushes.get(index, 0.0)
        components.append(complex(np.mean(broadcast[3 * recorded + 1] * demodulate)))
    return components


def growth_per_link(chain: ChainModel, vehicle: int, w: np.ndarray) -> np.ndarray:
    """The spectral radius of ``vehicle``'s T(w): how much a disturbance at w grows per link far down a
    long string of vehicles like it (whatever the string's first links do)."""
    return _growth_per_link(chain.vehicle(vehicle), np.asarray(w, dtype=float), chain.step, chain.lifting_period())


def _growth_per_link(vehicle: Vehicle, w: np.ndarray, step: float, period: int) -> np.ndarray:
    """``growth_per_link`` of one vehicle at each of ``w``: the spectral radius of T(w)."""
    t, _ = receiver_maps(Lifted(w, step, period), vehicle)
    return np.abs(np.linalg.eigvals(t)).max(axis=-1)


@functools.lru_cache(maxsize=64)  # a few frequencies each (a cascade's probes): small
def lifted_maps(vehicle: Vehicle, frequencies: bytes, step: float, period: int) -> tuple[np.ndarray, np.ndarray]:
    """``receiver_maps`` of ``vehicle`` at the float64 frequencies packed in ``frequencies``, remembered
    (read-only): a cascade's interior vehicles are alike, and a map's runs repeat them."""
    lift = Lifted(np.frombuffer(frequencies, dtype=float), step, period)
    t, u = receiver_maps(lift, vehicle)
    t.flags.writeable = u.flags.writeable = False
    return t, u


# Growth per link above 1 by less than this is 1: rho(w) -> 1 as w -> 0 for every law (the lifting is
# computed to ~1e-12); a real excess near the boundary is 1e-4 or more on the frequency grid below.
GROWTH_TOLERANCE = 1e-9
# The peak search's first, log-spaced scan (11 % apart), then four rounds of 21 points between the best
# one's neighbours: on the study's 363 (law, delay, loss) cases it finds the peaks of a 600-point scan to
# 1e-9 and the same verdicts, at a third of the cost (a map computes hundreds of peaks).
COARSE_FREQUENCIES = 100


@dataclass(frozen=True)
class PeakGrowth:
    """The cascade's peak: the largest growth per link far down the string (the spectral radius of T(w))
    over all frequencies, and where."""

    gain: float  # max over w of the growth per link
    frequency: float  # rad/s where it is reached (0: the supremum is the limit w -> 0, where it is 1)

    @property
    def string_stable(self) -> bool:
        return self.gain <= 1.0 + GROWTH_TOLERANCE


def peak_growth(chain: ChainModel, vehicle: int) -> PeakGrowth:
    """The largest growth per link over w. T depends on w only through e^{j w P h}, so w in (0, pi/(P h)]
    covers every frequency; ``COARSE_FREQUENCIES`` log-spaced points from 1e-3 rad/s, refined four times
    around the best."""
    return _peak_growth(chain.vehicle(vehicle), chain.step, chain.lifting_period())


@functools.lru_cache(maxsize=256)
def _peak_growth(vehicle: Vehicle, step: float, period: int) -> PeakGrowth:
    """``peak_growth`` of one vehicle, remembered: a map's runs repeat its grid's vehicles, and acc's
    vehicle is the same at every delay and loss (its sensor is a plain connection)."""
    top = math.pi / (period * step)
    w = np.geomspace(1e-3, top, COARSE_FREQUENCIES)
    for _ in range(4):
        gain = _growth_per_link(vehicle, w, step, period)
        best = int(np.argmax(gain))
        if best == 0 and gain[0] <= 1.0 + GROWTH_TOLERANCE:
            return PeakGrowth(1.0, 0.0)
        top_w, top_gain = w[best], gain[best]
        w = np.linspace(w[max(best - 1, 0)], w[min(best + 1, len(w) - 1)], 21)
    return PeakGrowth(float(top_gain), float(top_w))


def largest_stable_delay(with_delay: Callable[[float], ChainModel], vehicle: int, step: float,
                         longest: float = 2.0) -> float | None:
    """The delay (s, on the grid of ``step``) of every link up to which the string is stable at every delay of
    the grid, scanning from 0 up to ``longest`` (not a bisection: the growth jumps as the delay crosses the
    beacon grid); None if unstable even without delay, ``longest`` if stable up to there. ``with_delay(d)``:
    the chain with every link's delay d (``chain_model`` of the config so changed)."""
    stable = None
    for steps in range(0, int(round(longest / step)) + 1):
        delay = steps * step
        if not peak_growth(with_delay(delay), vehicle).string_stable:
            return stable
        stable = delay
    return longest


def smallest_stable_time_gap(chain: ChainModel, vehicle: int, longest: float = 100.0) -> float | None:
    """The smallest time gap h (s, to 1e-4 relative) from which the cascade is string stable (acc, cacc; the
    rest kept), by bisection: the peak falls as h grows. None if not stable up to ``longest``; 1e-3 if
    stable from there."""
    receiver = chain.vehicle(vehicle)
    period = chain.lifting_period()

    def stable(time_gap: float) -> bool:
        return _peak_growth(replace(receiver, time_gap=time_gap), chain.step, period).string_stable

    low, high = 1e-3, longest
    if not stable(high):
        return None
    if stable(low):
        return low
    while high - low > 1e-4 * high:
        middle = math.sqrt(low * high)  # geometric: h spans five decades
        low, high = (low, middle) if stable(middle) else (middle, high)
    return high


def exact_lines(chain: ChainModel, vehicle: int, with_delay: Callable[[float], ChainModel]) -> list[str]:
    """`platoon analyze`'s lines for the sampled-data cascade of ``chain``, or the reason it does not apply;
    ``with_delay``: as ``largest_stable_delay`` takes it (cacc's scan of the link delay)."""
    if chain.missing is not None:
        return [f"  sampled-data cascade: not computed for {chain.missing}; the verdict is the phase-averaged model's"]
    period = chain.lifting_period()
    growth = peak_growth(chain, vehicle)
    where = f"at {growth.frequency:.4g} rad/s" if growth.frequency > 0 else "as w -> 0 (<= 1 everywhere)"
    verdict = "string stable" if growth.string_stable else "NOT string stable"
    lines = [f"  sampled-data cascade, exact on the {chain.step:g} s step grid (lifted over "
             f"{period} step(s)): growth per link far down the string peaks at {growth.gain:.4f} {where}: {verdict}"]
    receiver = chain.vehicle(vehicle)
    if receiver.law in ("acc", "cacc"):
        least = smallest_stable_time_gap(chain, vehicle)
        lines.append("  (cascade) not string stable for any time_gap up to 100 s with these links" if least is None else
                     f"  (cascade) string stable for time_gap >= {least:.4g} s with these links")
    if receiver.law == "cacc":
        most = largest_stable_delay(with_delay, vehicle, chain.step)
        lines.append(f"  (cascade) with time_gap = {receiver.time_gap:g} s not string stable even without a link "
                     "delay" if most is None else f"  (cascade) with time_gap = {receiver.time_gap:g} s string "
                     f"stable for every link delay on the step grid up to {most:.4g} s")
    return lines
