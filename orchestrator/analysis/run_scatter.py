"""A single run's predicted scatter: the driven cascade's first and second moments over the delivery patterns.

With losses a run's gain is a random variable: which beacon each receiver uses is a draw. The sampled-data
cascade (``sampled_chain``) gives its mean, the periodic steady state of the mean over the losses. This module
gives its scatter, for the same semantics (a line, kinematic vehicles, the Jacobi master, beacon periods that
are multiples of the step, no jitter; ``chain_model.ChainModel.missing``) and independent losses, by stepping the
linearized string in time from the first push to the end of the fitting window:

- the state z holds every modelled vehicle's (x, V_s), its inputs of the step before (the speed rate it
  outputs needs them), each push as a rotating phasor (so the sinusoids are states, and the step is linear),
  and per link the beacons in flight and the view in use (the newest delivered beacon moved to the current
  step: its extrapolation polynomial, as in ``loop_moments``);
- at each step every link whose beacon falls due delivers it (the view becomes the beacon, aged by the link's
  lag) with probability 1 - loss, else keeps its view (aged one step). The links act on disjoint parts of the
  state, each reading only its own beacons and view, so the step over all of them is
  M(delta) = M_mean + sum_L e_L Delta_L with independent e_L of mean 0 and variance p_L (1 - p_L);
- the **mean** m evolves by M_mean (what the cascade's steady state is the limit of), the **second moment**
  Q = E[z z^T] exactly by Q -> M_mean Q M_mean^T + sum_L p_L (1 - p_L) Delta_L Q Delta_L^T (independent
  jumps: Costa, Fragoso and Marques, *Discrete-Time Markov Jump Linear Systems*, 2005, ch. 3). Not the mean's
  square: each lost beacon's noise enters, and is carried on by the mean dynamics of everything after it.
- held links: a held position is V_c times its age behind the steady state the model's deviations are taken
  from. Where one crosses a lossy link (the paper's law) its age is random, an affine forcing the losses make
  whatever the probe (metres of gap noise at 40 % loss): the state then carries a constant 1, and the string
  is stepped from the run's start (at rest), as the run is, the pushes' phasors added at the first push;
- a run's headline at a probe is (amplitude of the stretch's last vehicle / its first) ** (1 / links), the
  amplitudes fitted by least squares over the window (``headline.probe_amplitudes``). The fitted (cos, sin)
  coefficients are linear in the records: accumulated beside the state, their mean and covariance are read
  exactly. The ratio is not linear in them: the coefficients are taken Gaussian (sums over hundreds of the
  noise's correlation times), and the growth's mean and standard deviation are those of fixed draws of them.
  Where the noise is most of an amplitude (held paper law) a run's growth centres off the mean run's: such a
  probe is *buried* (``Scatter.buried``), not judged.

This is the scatter of one run of this config over its delivery patterns, predicted, not measured; a run's
batch means (``headline``) measure the same from the run itself. Pure computation (numpy), no I/O.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass

import numpy as np
from scipy import sparse

from orchestrator.analysis.chain_model import PLAIN, ChainModel, Timing
from orchestrator.analysis.loop_moments import shift_view
from orchestrator.analysis.moment_blocks import Block, compose
from orchestrator.analysis.sampled_chain import step_maps


# The second moment is a state x state matrix stepped over every step of the run: the study (7 vehicles, 190 states,
# 15 566 steps) costs 6e8 state^2 x steps, 2-3 s on a 2-core machine (blocks of steps, moment_blocks). Beyond these
# the scatter is not predicted (the measured one stands in), rather than a command that runs for hours or fills the
# memory.
MOST_STATE = 1000
MOST_WORK = 2e10
MOST_PHASES = 5000  # step maps kept (a state x state mean map and the noises' columns each)
BURIED = 1.0  # a probe whose runs centre off the cascade by more than this many of their sigmas is buried in noise
DRAWS = 200_000  # of the fitted coefficients (_growth_draws): the growth's standard deviation to 0.2 % of it


@dataclass(frozen=True)
class Channel:
    """What a receiver reads through one link (or plain connection): the sender's message at each beacon, its
    lag and beacon period in steps, its loss; the state rows of its beacons in flight (slots) and of its view."""

    kind: str  # "motion": (x, speed, rate) of the sender; "paper": (speed, rate, gap, gap rate) of a follower
    role: str  # "sensor" (acc, cacc: the sensed position), "speed" (cacc), "paper" (the follower's message), "seen"
    sender: int
    receiver: int
    lag: int
    every: int
    loss: float
    slots: tuple[range, ...]
    view: range


class _Rows:
    """Allocates the state's rows by name."""

    def __init__(self) -> None:
        self.size = 0

    def take(self, count: int) -> range:
        taken = range(self.size, self.size + count)
        self.size += count
        return taken


@dataclass
class Scatter:
    """Per probe frequency: the mean run's growth per link over the stretch and its predicted standard deviation."""

    frequencies: list[float]
    growth: list[float]
    sigma: list[float]
    noise: list[float] | None = None  # per probe: the fitted amplitude's noise over the amplitude, the larger end's
    expected: list[float] | None = None  # per probe: a run's growth averaged over the losses (not the mean run's)

    def buried(self) -> dict[float, str]:
        """The probes a run measures its noise at, not the probe: where a run's growth centres off the mean
        run's (the cascade's) by more than its own standard deviation (``BURIED``). There the fitted amplitude
        at an end of the stretch is mostly noise (its noise over it given), the headline's ratio of two such
        amplitudes is biased towards the noise's own, and "mean +- sigma" no longer describes a run."""
        found = {}
        for k, w in enumerate(self.frequencies):
            if self.expected is None or abs(self.expected[k] - self.growth[k]) <= BURIED * self.sigma[k]:
                continue
            found[w] = (f"buried in the noise of the losses: a run's growth centres on {self.expected[k]:.3g}, not "
                        f"the cascade's {self.growth[k]:.3g} (sigma {self.sigma[k]:.2g}; the fitted amplitude's noise "
                        f"is {self.noise[k]:.2g} times the probe's at an end of the stretch)")
        return found


class LinearString:
    """The linearized string of one chain in time (module docstring), from the step of the first push on:
    ``vehicles`` (0: the virtual target) of ``chain``."""

    def __init__(self, chain: ChainModel, vehicles: list[int]) -> None:
        self.h, self.extrapolate = chain.step, chain.extrapolate
        rows = _Rows()
        self.vehicles = {i: chain.vehicle(i) for i in vehicles if i > 0}
        self.x = {i: rows.take(1)[0] for i in vehicles}  # position (the target: under acc and cacc)
        self.v = {i: rows.take(1)[0] for i in self.vehicles}  # speed loop state V_s
        self.before = {i: rows.take(3) for i in self.vehicles}  # the inputs of the step before (tau^0..2)
        self.pushes = [(d.vehicle, d.frequency, d.value, d.start, rows.take(2)) for d in chain.pushes
                       if d.kind == "speed" and d.vehicle in vehicles]
        self.pushed_before = {i: rows.take(1)[0] for i in vehicles}  # p(k - 1)
        self.channels = [self._channel(rows, *wanted) for wanted in self._wanted()]
        # held links: a held position is V_c times its age behind the sender's steady state, an affine forcing
        # whose random part the losses create whatever the probe; a constant state carries it (a row of ones)
        self.one = rows.take(1)[0] if self.stale_positions() else None
        self.speed = chain.speed
        self.size = rows.size

    def stale_positions(self) -> bool:
        """Whether a position is held across a lossy link (the paper law's gaps through held links): its age is
        then random, and V_c times it a noise in the gap the linear deviations alone do not have."""
        return not self.extrapolate and any(c.role == "seen" and c.loss > 0.0 for c in self.channels)

    def _wanted(self) -> list[tuple[str, str, int, int, Timing]]:
        """(kind, role, sender, receiver, the link's timing) of every input of the model: the links each
        vehicle's law reads through (``chain_model.Vehicle``)."""
        wanted: list[tuple[str, str, int, int, Timing]] = []
        for i, v in self.vehicles.items():
            if v.law in ("acc", "cacc"):
                wanted.append(("motion", "sensor", i - 1, i, PLAIN))
                if v.law == "cacc":
                    wanted.append(("motion", "speed", i - 1, i, v.comm))
            elif not v.last:
                wanted.append(("paper", "paper", i + 1, i, v.comm))
                wanted.append(("motion", "seen", i, i + 1, v.gap_link))  # the follower's view of i: its gap
        return wanted

    def _channel(self, rows: _Rows, kind: str, role: str, sender: int, receiver: int, link: Timing) -> Channel:
        width = 3 if kind == "motion" else 4
        slots = tuple(rows.take(width) for _ in range(link.lag // link.every + 1))
        return Channel(kind, role, sender, receiver, link.lag, link.every, link.loss, slots, rows.take(width))

    # --- the step, on symbolic rows (each a vector over the state at the step's start) -------------------

    def outputs(self, z: np.ndarray, i: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Component i's (x, speed, speed rate) at t_k, from its state and its inputs of the step before."""
        if i not in self.vehicles:  # the acc/cacc target: V_c plus its push
            return z[self.x[i]], z[self.pushed_before[i]], np.zeros_like(z[self.x[i]])
        a, _, push = self.vehicles[i].loop()
        before = self.before[i]
        rate = (a[1, 0] * z[self.x[i]] + a[1, 1] * z[self.v[i]] + sum(self.h**q * z[before[q]] for q in range(3))
                + push[1] * z[self.pushed_before[i]])
        return z[self.x[i]], z[self.v[i]] + z[self.pushed_before[i]], rate

    def _gap_message(self, z: np.ndarray, c: Channel) -> list[np.ndarray]:
        """A paper follower's message at its beacon: its speed and rate, and its gap to the vehicle ahead (its
        view of it over the step before, at that step's end, minus its own position) and the gap's rate."""
        follower, ahead = c.sender, c.receiver
        seen = next(s for s in self.channels if s.role == "seen" and s.sender == ahead and s.receiver == follower)
        x_seen, v_seen, a_seen = (z[r] for r in seen.view)
        x, speed, rate = self.outputs(z, follower)
        if self.extrapolate:
            gap = x_seen + self.h * v_seen + 0.5 * self.h * self.h * a_seen - x
            gap_rate = v_seen + self.h * a_seen - speed
        else:
            gap, gap_rate = self._stale(x_seen, z, 1) - x, v_seen - speed
        return [speed, rate, gap, gap_rate]

    def _stale(self, x: np.ndarray, z: np.ndarray, steps: int) -> np.ndarray:
        """A held position ``steps`` steps older against the steady state it is a deviation from: V_c steps h
        behind (nothing where the model keeps no row of ones: no held position crosses a lossy link)."""
        if self.one is None:
            return x
        return x - self.speed * steps * self.h * z[self.one]

    def _aged(self, z: np.ndarray, view: list[np.ndarray], kind: str, steps: int) -> list[np.ndarray]:
        """A view moved ``steps`` steps on (held: as it is, its position ``steps`` steps older)."""
        if steps == 0:
            return view
        if not self.extrapolate:
            return [self._stale(view[0], z, steps), *view[1:]] if kind == "motion" else view
        if kind == "motion":  # x, speed, rate: order 2
            return shift_view(view, steps, self.h)
        return shift_view(view[:2], steps, self.h) + shift_view(view[2:], steps, self.h)  # speed and gap: order 1

    def broadcast(self, z: np.ndarray, k: int) -> np.ndarray:
        """Every sender whose beacon is due at step k puts its message in its link's slot."""
        new = z.copy()
        for c in self.channels:
            if k % c.every == 0:
                message = self.outputs(z, c.sender) if c.kind == "motion" else self._gap_message(z, c)
                slot = c.slots[(k // c.every) % len(c.slots)]
                for row, value in zip(slot, message):
                    new[row] = value
        return new

    def deliveries(self, k: int) -> list[Channel]:
        return [c for c in self.channels if (k - c.lag) % c.every == 0]

    def delivered(self, z: np.ndarray, c: Channel, k: int) -> list[np.ndarray]:
        """The view of ``c`` at step k if its due beacon arrives."""
        slot = c.slots[((k - c.lag) // c.every) % len(c.slots)]
        return self._aged(z, [z[r] for r in slot], c.kind, c.lag)

    def kept(self, z: np.ndarray, c: Channel) -> list[np.ndarray]:
        """The view of ``c`` at step k if no beacon arrives: the one of the step before, aged a step."""
        return self._aged(z, [z[r] for r in c.view], c.kind, 1)

    def advance(self, z: np.ndarray, k: int) -> np.ndarray:
        """The inputs over step k from the views, then the exact step of every vehicle and push."""
        new = z.copy()
        h = self.h
        for i, v in self.vehicles.items():
            a, gains, push_vector = v.loop()
            forcing = [np.zeros_like(z[0]) for _ in range(3)]
            for c in (c for c in self.channels if c.receiver == i and c.role != "seen"):
                view = [z[r] for r in c.view]
                if c.role == "sensor":  # the sensed position, tau^0..2
                    terms = [(gains["sensor"], [view[0], view[1], 0.5 * view[2]] if self.extrapolate else [view[0]])]
                elif c.role == "speed":  # cacc's communicated speed
                    terms = [(gains["speed"], [view[1], view[2]] if self.extrapolate else [view[1]])]
                else:  # the paper law: the follower's speed and gap
                    terms = [(gains["speed"], [view[0], view[1]] if self.extrapolate else [view[0]]),
                             (gains["gap"], [view[2], view[3]] if self.extrapolate else [view[2]])]
                for gain, polynomial in terms:
                    for q, row in enumerate(polynomial):
                        forcing[q] = forcing[q] + gain * row
            flow, gammas = step_maps(a, h)
            state = [z[self.x[i]], z[self.v[i]]]
            pushed = self._push(z, i)
            for r, row in enumerate((self.x[i], self.v[i])):
                new[row] = (flow[r, 0] * state[0] + flow[r, 1] * state[1]
                            + sum(gammas[q][r, 1] * forcing[q] for q in range(3)) + (gammas[0] @ push_vector)[r] * pushed)
            for q in range(3):
                new[self.before[i][q]] = forcing[q]
        for i in self.x:
            if i not in self.vehicles:
                new[self.x[i]] = z[self.x[i]] + h * self._push(z, i)
            new[self.pushed_before[i]] = self._push(z, i)
        for _, w, _, _, (c, s) in self.pushes:
            new[c] = math.cos(w * h) * z[c] - math.sin(w * h) * z[s]
            new[s] = math.sin(w * h) * z[c] + math.cos(w * h) * z[s]
        return new

    def _push(self, z: np.ndarray, i: int) -> np.ndarray:
        """p_i(k): the sum of vehicle i's sinusoids at t_k (their phasors' imaginary parts)."""
        total = np.zeros_like(z[0])
        for vehicle, _, _, _, (_, s) in self.pushes:
            if vehicle == i:
                total = total + z[s]
        return total

    def at_rest(self) -> np.ndarray:
        """The state at the run's start: every vehicle at its steady state (and the row of ones at 1)."""
        z = np.zeros(self.size)
        if self.one is not None:
            z[self.one] = 1.0
        return z

    def initial(self, k: int) -> np.ndarray:
        """The pushes' phasors at step k (the rest zero): what the pushes started before step k add to the state."""
        z = np.zeros(self.size)
        for _, w, value, start, (c, s) in self.pushes:
            phase = w * (k * self.h - start)
            z[c], z[s] = value * math.cos(phase), value * math.sin(phase)
        return z


@dataclass(frozen=True)
class _StepMaps:
    """One step as matrices over the state: the mean map, and per lossy link due (p (1 - p), its noise's rows
    through the rest of the step, its noise's rows at the view)."""

    mean: sparse.csr_matrix
    noises: tuple[tuple[float, np.ndarray, np.ndarray], ...]


def _step_maps(model: LinearString, k: int) -> _StepMaps:
    eye = np.eye(model.size)
    before = model.broadcast(eye, k)
    due = model.deliveries(k)
    mean, noise_rows = before.copy(), []
    for c in model.channels:
        kept = model.kept(before, c)
        if c not in due:
            arrived = kept
        else:
            delivered = model.delivered(before, c, k)
            arrived = [(1.0 - c.loss) * d + c.loss * q for d, q in zip(delivered, kept)]
            if c.loss > 0.0:
                noise_rows.append((c, np.array([d - q for d, q in zip(delivered, kept)])))
        for row, value in zip(c.view, arrived):
            mean[row] = value
    after = model.advance(eye, k)
    noises = tuple((c.loss * (1.0 - c.loss), after[:, list(c.view)], rows) for c, rows in noise_rows)
    return _StepMaps(sparse.csr_matrix(after @ mean), noises)


@dataclass(frozen=True)
class Stretch:
    """What a run's headline measures: the vehicles along the clean stretch (first, ..., last), the probes, the
    records (every ``every`` steps) inside ``window``."""

    vehicles: list[int]
    frequencies: list[float]
    window: tuple[float, float]
    every: int


def _record_steps(model: LinearString, stretch: Stretch, first: int) -> list[int]:
    h, (start, end) = model.h, stretch.window
    last = int(math.floor(end / h + 1e-9))
    return [k for k in range(first, last + 1) if k % stretch.every == 0 and start - 1e-9 <= k * h <= end + 1e-9]


def _design(times: np.ndarray, frequencies: list[float]) -> np.ndarray:
    """The least-squares fit of ``headline.probe_amplitudes`` as a matrix: coefficients = it @ records."""
    columns = [f(w * times) for w in frequencies for f in (np.cos, np.sin)] + [np.ones(len(times))]
    return np.linalg.pinv(np.column_stack(columns))


class _Maps:
    """The step maps by phase (they repeat with the beacons and the slots)."""

    def __init__(self, model: LinearString, every: int) -> None:
        self.model, self.every = model, every  # every: the records' steps, the blocks' length
        self.period = math.lcm(1, *(c.every * len(c.slots) for c in model.channels))
        self._by_phase: dict[int, _StepMaps] = {}
        self._blocks: dict[tuple[int, int], Block] = {}

    def __call__(self, k: int) -> _StepMaps:
        phase = k % self.period
        if phase not in self._by_phase:
            self._by_phase[phase] = _step_maps(self.model, k)
        return self._by_phase[phase]

    def block(self, k: int, length: int) -> Block:
        """Steps k .. k + length - 1 as one map of the second moment (``moment_blocks``)."""
        key = (k % self.period, length)
        if key not in self._blocks:
            self._blocks[key] = compose([self(k + i) for i in range(length)])
        return self._blocks[key]


def _blocks(start: int, stop: int, every: int) -> list[tuple[int, int]]:
    """(first step, steps) of blocks covering steps start .. stop - 1, each within one stretch of ``every`` steps
    from a multiple of it (the records' steps: a block never passes one)."""
    found, k = [], start
    while k < stop:
        end = min(stop, (k // every + 1) * every)
        found.append((k, end - k))
        k = end
    return found


def predicted_scatter(chain: ChainModel, stretch: Stretch) -> Scatter | str:
    """The mean run's headline growth per probe over ``stretch`` and its predicted standard deviation over the
    delivery patterns (module docstring), or why it is not predicted."""
    if chain.missing is not None:
        return f"not predicted for {chain.missing}"
    if chain.bursty:
        return "not predicted for burst losses (a beacon's loss depends on the one before)"
    starts = {d.start for d in chain.pushes}
    if len(starts) != 1 or any(d.kind != "speed" for d in chain.pushes):
        return "not predicted for pushes other than speed sinusoids that all start together"
    law = chain.law(max(1, min(stretch.vehicles)))
    if any(chain.law(i) != law for i in range(1, chain.count + 1)):
        return "not predicted for a platoon of mixed speed laws"
    span = (range(0, max(stretch.vehicles) + 1) if law in ("acc", "cacc")
            else range(min(stretch.vehicles), chain.count + 1))
    model = LinearString(chain, list(span))
    first = int(math.ceil(starts.pop() / model.h - 1e-9))
    records = _record_steps(model, stretch, first)
    if not records:
        return "not predicted: no record inside the fitting window"
    stepped = records[-1] - (first if model.one is None else 0)  # stale positions: from the run's start (_start)
    work = stepped * model.size**2
    if model.size > MOST_STATE or work > MOST_WORK:
        return (f"not predicted: a state of {model.size} over {stepped} steps (at most {MOST_STATE}, and "
                f"{MOST_WORK:.0e} state^2 x steps: the study's is 6e8, 2-3 s)")
    maps = _Maps(model, stretch.every)
    if maps.period > MOST_PHASES:
        return f"not predicted: its step maps repeat only every {maps.period} steps (at most {MOST_PHASES} are kept)"
    fit = _design(np.array(records) * model.h, stretch.frequencies)
    ends = (stretch.vehicles[0], stretch.vehicles[-1])
    speeds = {i: model.outputs(np.eye(model.size), i)[1] for i in ends}  # rows: the recorded speed
    links, probes = len(stretch.vehicles) - 1, len(stretch.frequencies)
    if not any(c.loss > 0.0 for c in model.channels):  # nothing random: a run is its mean
        mean = _mean_records(model, maps, first, records, speeds)
        amplitude = {i: fit[:2 * probes] @ mean[i] for i in ends}
        growth = [_headline_growth(amplitude[ends[0]][2 * k:2 * k + 2], amplitude[ends[1]][2 * k:2 * k + 2], links)
                  for k in range(probes)]
        return Scatter(list(stretch.frequencies), growth, [0.0] * probes)
    mean, second = _fit_moments(model, maps, first, records, speeds, fit[:2 * probes])
    growth, sigma, noise, expected = [], [], [], []
    for k in range(probes):
        wanted = [2 * k, 2 * k + 1, 2 * probes + 2 * k, 2 * probes + 2 * k + 1]  # (cos, sin) of the first, the last
        mu, covariance = mean[wanted], second[np.ix_(wanted, wanted)] - np.outer(mean[wanted], mean[wanted])
        growth.append(_headline_growth(mu[:2], mu[2:], links))
        average, deviation = _growth_draws(mu, covariance, links)
        sigma.append(deviation)
        expected.append(average)
        noise.append(max(math.sqrt(max(np.trace(covariance[e:e + 2, e:e + 2]), 0.0) / 2.0) / np.hypot(*mu[e:e + 2])
                         for e in (0, 2)))
    return Scatter(list(stretch.frequencies), growth, sigma, noise, expected)


@functools.cache
def _normals() -> np.ndarray:
    return np.random.default_rng(52).standard_normal((DRAWS, 4))


def _headline_growth(first: np.ndarray, last: np.ndarray, links: int) -> float:
    """The headline at one probe from the (cos, sin) coefficients of the stretch's first and last vehicle."""
    return float((np.hypot(*last) / np.hypot(*first)) ** (1.0 / links))


def _growth_draws(mu: np.ndarray, covariance: np.ndarray, links: int) -> tuple[float, float]:
    """The mean and standard deviation of (|c_last| / |c_first|) ^ (1 / links), c = the fitted (cos, sin) coefficients,
    whose mean ``mu`` and covariance (4 x 4) are exact. A fit over the window is a sum over hundreds of the
    noise's correlation times: the coefficients are taken Gaussian, and the growth's deviation is drawn, not
    linearized (to first order it is growth x the gradient of its log; that overstates it where the noise is a
    fair part of an amplitude: the held paper law's at 0.3 rad/s, 0.97 against 0.24 measured over six seeds).
    Fixed draws: the same config gives the same number, to 0.2 % of it."""
    values, vectors = np.linalg.eigh(0.5 * (covariance + covariance.T))
    root = vectors * np.sqrt(np.clip(values, 0.0, None))
    draws = mu + _normals() @ root.T
    growth = (np.hypot(draws[:, 2], draws[:, 3]) / np.hypot(draws[:, 0], draws[:, 1])) ** (1.0 / links)
    return float(growth.mean()), float(growth.std())


def _start(model: LinearString, maps: _Maps, first: int, square: bool) -> tuple[np.ndarray, np.ndarray | None]:
    """The state's mean and (``square``) second moment at the first push's step. Without stale held positions
    nothing moves before it: the pushes' phasors. With them the losses stir the string from the run's start
    (step 0, at rest) on, and the first push meets that stirred string: stepped from step 0, the phasors (not
    random) added at the push."""
    pushes = model.initial(first)
    if model.one is None:
        return pushes, (np.outer(pushes, pushes) if square else None)
    m = model.at_rest()
    q = np.outer(m, m) if square else None
    for k, length in _blocks(0, first, maps.every):
        block = maps.block(k, length)
        if square:
            q = block.second_moment(q)
        m = block.mean @ m
    if square:
        q = q + np.outer(m, pushes) + np.outer(pushes, m) + np.outer(pushes, pushes)
    return m + pushes, q


def _mean_records(model: LinearString, maps: _Maps, first: int, records: list[int],
                  speeds: dict[int, np.ndarray]) -> dict[int, np.ndarray]:
    """The mean run's recorded speeds of the stretch's ends."""
    m, found, wanted = _start(model, maps, first, False)[0], {i: [] for i in speeds}, set(records)
    for k in range(first, records[-1] + 1):
        if k in wanted:
            for i, row in speeds.items():
                found[i].append(row @ m)
        m = maps(k).mean @ m
    return {i: np.array(values) for i, values in found.items()}


def _fit_moments(model: LinearString, maps: _Maps, first: int, records: list[int], speeds: dict[int, np.ndarray],
                 fit: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The mean and second moment over the delivery patterns of the fitted coefficients (``fit`` @ the records of
    each end vehicle, the first's then the last's): the state's second moment stepped exactly, the coefficients
    (linear functionals of the records) accumulated beside the state."""
    n, count = model.size, 2 * len(fit)
    m, q = _start(model, maps, first, True)
    total_mean, cross, total_square = np.zeros(count), np.zeros((count, n)), np.zeros((count, count))
    index = {k: r for r, k in enumerate(records)}
    for k, length in [*_blocks(first, records[-1], maps.every), (records[-1], 0)]:
        if k in index:  # the functionals take this record: g^T z, with z's moments m and q
            g = np.vstack([fit[:, index[k]][:, None] * speeds[i][None, :] for i in speeds])  # count x n
            total_square += g @ q @ g.T + cross @ g.T + g @ cross.T
            cross += g @ q
            total_mean += g @ m
        if length:
            block = maps.block(k, length)
            cross = (block.mean @ cross.T).T
            # the functionals' cross moment with the state picks up the noise too, but only through the state: the
            # noise of a step is independent of everything before, so E[total * noise] = 0
            q, m = block.second_moment(q), block.mean @ m
    return total_mean, total_square
