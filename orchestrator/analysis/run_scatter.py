"""A single run's predicted scatter: the driven cascade's first and second moments over the delivery patterns.

With losses a run's gain is a random variable: which beacon each receiver uses is a draw. The sampled-data
cascade (``sampled_chain``) gives its mean, the periodic steady state of the mean over the losses. This module
gives its scatter, for the same semantics (a line, kinematic vehicles, the Jacobi master, beacon periods that
are multiples of the step, no jitter; ``sampled_chain.exact_applies``) and independent losses, by stepping the
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
- a run's headline at a probe is (amplitude of the stretch's last vehicle / its first) ** (1 / links), the
  amplitudes fitted by least squares over the window (``headline.probe_amplitudes``). To first order in the
  deviations from the mean, its logarithm is a fixed linear functional of the recorded speeds; accumulated
  in the state, its variance is read from Q at the end: the predicted standard deviation of a single run's
  headline is growth x sqrt(that variance).

This is the scatter of one run of this config over its delivery patterns, predicted, not measured; a run's
batch means (``headline``) measure the same from the run itself. Pure computation (numpy), no I/O.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
from scipy import sparse

from orchestrator.analysis.loop_moments import shift_view
from orchestrator.analysis.sampled_chain import exact_applies, step_maps, timing_of, vehicle_of

if TYPE_CHECKING:
    from orchestrator.scenario.config import Config


# The second moment is a state x state matrix stepped over every step of the run: the study (7 vehicles, 190 states,
# 15 566 steps) costs 6e8 state^2 x steps, 2-7 s on a 2-core machine. Beyond these the scatter is not predicted
# (the measured one stands in), rather than a command that runs for hours or fills the memory.
MOST_STATE = 1000
MOST_WORK = 2e10
MOST_PHASES = 5000  # step maps kept (a state x state mean map and the noises' columns each)


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


class LinearString:
    """The linearized string of one config in time (module docstring), from the step of the first push on."""

    def __init__(self, config: "Config", vehicles: list[int]) -> None:
        self.config, self.h = config, config.simulation.step
        self.extrapolate = config.simulation.coupling == "extrapolate"
        rows = _Rows()
        self.vehicles = {i: vehicle_of(config, i) for i in vehicles if i > 0}
        self.x = {i: rows.take(1)[0] for i in vehicles}  # position (the target: under acc and cacc)
        self.v = {i: rows.take(1)[0] for i in self.vehicles}  # speed loop state V_s
        self.before = {i: rows.take(3) for i in self.vehicles}  # the inputs of the step before (tau^0..2)
        self.pushes = [(d.vehicle, d.frequency, d.value, d.start, rows.take(2)) for d in config.disturbance
                       if d.kind == "speed" and d.vehicle in vehicles]
        self.pushed_before = {i: rows.take(1)[0] for i in vehicles}  # p(k - 1)
        self.channels = [self._channel(rows, *wanted) for wanted in self._wanted()]
        self.size = rows.size

    def _wanted(self) -> list[tuple[str, str, int, int, object]]:
        """(kind, role, sender, receiver, the link's (direction, vehicle) or "plain") of every input of the model."""
        wanted: list[tuple[str, str, int, int, object]] = []
        for i, v in self.vehicles.items():
            if v.law in ("acc", "cacc"):
                wanted.append(("motion", "sensor", i - 1, i, "plain"))
                if v.law == "cacc":
                    wanted.append(("motion", "speed", i - 1, i, ("backward", i)))
            elif not v.last:
                wanted.append(("paper", "paper", i + 1, i, ("forward", i + 1)))
                wanted.append(("motion", "seen", i, i + 1, ("backward", i + 1)))  # the follower's view of i: its gap
        return wanted

    def _channel(self, rows: _Rows, kind: str, role: str, sender: int, receiver: int, link) -> Channel:
        if link == "plain":
            lag, every, loss = 0, 1, 0.0
        else:
            timing, resolved = timing_of(self.config, *link), self.config.resolve_link(*link)
            lag, every = timing.lag, timing.every
            loss = 0.0 if resolved.perfect else resolved.loss
        width = 3 if kind == "motion" else 4
        slots = tuple(rows.take(width) for _ in range(lag // every + 1))
        return Channel(kind, role, sender, receiver, lag, every, loss, slots, rows.take(width))

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
            gap, gap_rate = x_seen - x, v_seen - speed
        return [speed, rate, gap, gap_rate]

    def _aged(self, view: list[np.ndarray], kind: str, steps: int) -> list[np.ndarray]:
        """A view moved ``steps`` steps on (held: as it is)."""
        if not self.extrapolate or steps == 0:
            return view
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
        return self._aged([z[r] for r in slot], c.kind, c.lag)

    def kept(self, z: np.ndarray, c: Channel) -> list[np.ndarray]:
        """The view of ``c`` at step k if no beacon arrives: the one of the step before, aged a step."""
        return self._aged([z[r] for r in c.view], c.kind, 1)

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

    def initial(self, k: int) -> np.ndarray:
        """The deviation state at step k, before which nothing was pushed: the pushes' phasors only."""
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

    def __init__(self, model: LinearString) -> None:
        self.model = model
        self.period = math.lcm(1, *(c.every * len(c.slots) for c in model.channels))
        self._by_phase: dict[int, _StepMaps] = {}

    def __call__(self, k: int) -> _StepMaps:
        phase = k % self.period
        if phase not in self._by_phase:
            self._by_phase[phase] = _step_maps(self.model, k)
        return self._by_phase[phase]


def predicted_scatter(config: "Config", stretch: Stretch) -> Scatter | str:
    """The mean run's headline growth per probe over ``stretch`` and its predicted standard deviation over the
    delivery patterns (module docstring), or why it is not predicted."""
    missing = exact_applies(config)
    if missing is not None:
        return f"not predicted for {missing}"
    if any(not link.perfect and link.loss > 0.0 and link.burst > 1.0
           for link in (config.resolve_link(d, i) for d in ("backward", "forward")
                        for i in range(1, config.platoon.count + 1))):
        return "not predicted for burst losses (a beacon's loss depends on the one before)"
    starts = {d.start for d in config.disturbance}
    if len(starts) != 1 or any(d.kind != "speed" for d in config.disturbance):
        return "not predicted for pushes other than speed sinusoids that all start together"
    law = config.speed_law_of(max(1, min(stretch.vehicles)))
    if any(config.speed_law_of(i) != law for i in range(1, config.platoon.count + 1)):
        return "not predicted for a platoon of mixed speed laws"
    span = (range(0, max(stretch.vehicles) + 1) if law in ("acc", "cacc")
            else range(min(stretch.vehicles), config.platoon.count + 1))
    model = LinearString(config, list(span))
    first = int(math.ceil(starts.pop() / model.h - 1e-9))
    records = _record_steps(model, stretch, first)
    if not records:
        return "not predicted: no record inside the fitting window"
    work = (records[-1] - first) * model.size**2
    if model.size > MOST_STATE or work > MOST_WORK:
        return (f"not predicted: a state of {model.size} over {records[-1] - first} steps (at most {MOST_STATE}, and "
                f"{MOST_WORK:.0e} state^2 x steps: the study's is 6e8, 2-7 s)")
    maps = _Maps(model)
    if maps.period > MOST_PHASES:
        return f"not predicted: its step maps repeat only every {maps.period} steps (at most {MOST_PHASES} are kept)"
    fit = _design(np.array(records) * model.h, stretch.frequencies)
    ends = (stretch.vehicles[0], stretch.vehicles[-1])
    speeds = {i: model.outputs(np.eye(model.size), i)[1] for i in ends}  # rows: the recorded speed
    mean = _mean_records(model, maps, first, records, speeds)
    weights, growth = _log_growth_weights(fit, mean, ends, len(stretch.vehicles) - 1, len(stretch.frequencies))
    if not any(c.loss > 0.0 for c in model.channels):  # nothing random: a run is its mean
        return Scatter(list(stretch.frequencies), growth, [0.0] * len(growth))
    variance = _log_growth_variance(model, maps, first, records, speeds, weights)
    return Scatter(list(stretch.frequencies), growth, [g * math.sqrt(max(v, 0.0)) for g, v in zip(growth, variance)])


def _mean_records(model: LinearString, maps: _Maps, first: int, records: list[int],
                  speeds: dict[int, np.ndarray]) -> dict[int, np.ndarray]:
    """The mean run's recorded speeds of the stretch's ends."""
    m, found, wanted = model.initial(first), {i: [] for i in speeds}, set(records)
    for k in range(first, records[-1] + 1):
        if k in wanted:
            for i, row in speeds.items():
                found[i].append(row @ m)
        m = maps(k).mean @ m
    return {i: np.array(values) for i, values in found.items()}


def _log_growth_weights(fit: np.ndarray, mean: dict[int, np.ndarray], ends: tuple[int, int], links: int,
                        probes: int) -> tuple[dict[int, np.ndarray], list[float]]:
    """Per end vehicle, (probes x records) weights whose product with its recorded speeds is, to first order,
    the deviation of log(growth) at each probe; and the mean run's growth at each probe."""
    weights, amplitude = {}, {}
    for sign, i in zip((-1.0, 1.0), ends):
        coefficients = fit @ mean[i]
        rows = []
        for k in range(probes):
            a, b = coefficients[2 * k], coefficients[2 * k + 1]
            amplitude.setdefault(i, []).append(math.hypot(a, b))
            rows.append(sign * (a * fit[2 * k] + b * fit[2 * k + 1]) / (a * a + b * b) / links)
        weights[i] = np.array(rows)
    growth = [(amplitude[ends[1]][k] / amplitude[ends[0]][k]) ** (1.0 / links) for k in range(probes)]
    return weights, growth


def _log_growth_variance(model: LinearString, maps: _Maps, first: int, records: list[int],
                         speeds: dict[int, np.ndarray], weights: dict[int, np.ndarray]) -> list[float]:
    """The variance over the delivery patterns of each probe's log-growth functional: the state's second
    moment, stepped exactly, with the functionals accumulated beside the state."""
    n, probes = model.size, len(next(iter(weights.values())))
    m = model.initial(first)
    q = np.outer(m, m)
    total_mean, cross, total_square = np.zeros(probes), np.zeros((probes, n)), np.zeros((probes, probes))
    index = {k: r for r, k in enumerate(records)}
    for k in range(first, records[-1] + 1):
        if k in index:  # the functionals take this record: g^T z, with z's moments m and q
            g = sum(weights[i][:, index[k]][:, None] * speeds[i][None, :] for i in speeds)  # probes x n
            total_square += g @ q @ g.T + cross @ g.T + g @ cross.T
            cross += g @ q
            total_mean += g @ m
        step = maps(k)
        cross = (step.mean @ cross.T).T
        q_next = step.mean @ (step.mean @ q).T  # q is symmetric: M q M^T
        for weight, through, rows in step.noises:  # the noise is through @ rows @ z: of rank <= the view's width
            q_next += weight * (through @ (rows @ q @ rows.T) @ through.T)
        # the functionals' cross moment with the state picks up the noise too, but only through the state: the
        # noise of step k is independent of everything before, so E[total * noise] = 0
        q, m = q_next, step.mean @ m
    return list(np.diag(total_square) - total_mean**2)
