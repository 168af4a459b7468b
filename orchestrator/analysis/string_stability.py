"""String stability in closed form: the speed chain's G(jw) per speed law, through the links.

Each law passes a speed fluctuation from one vehicle to the next through a transfer function G(s)
(docs/model.md, section 12): the paper's law from the vehicle behind to the one ahead, acc and cacc
from the vehicle ahead to the one behind. The chain is string stable when |G(jw)| <= 1 at every
frequency (then no fluctuation grows along the platoon) and its own loop is stable.

What a vehicle knows of another vehicle reaches it as a *sample*: a message with the sender's
output_time, renewed every T seconds (the communication step, or a link's beacon period), at least
a0 seconds old when it arrives (a link's delay, rounded up to the communication grid, plus the step
the co-simulation's wiring adds), sometimes lost (the receiver then holds the older one). The receiver
uses the sample held (coupling "hold") or moved forward to its own time along the sender's rates
(coupling "extrapolate": the speed chain linearly, positions along an arc, i.e. a Taylor polynomial
of order 1 or 2 in the sample's age). So the signal the receiver sees is the sender's through

    P(s) = E[ e^{-sA} sum_{k<=m} (sA)^k / k! ],   A the age of the sample in use, m the order,

the fundamental-harmonic model of the sample-and-hold (the component of the output at the input's
frequency, averaged over the sampling phase and over the losses). It is exact for that component when
the loop is open; inside a loop it leaves out the aliases at w +- 2 pi k/T, which the speed loop filters
when w T << pi. With M(s) = E[e^{-sA}], E[(sA)^k e^{-sA}] = (-s)^k M^(k)(s), and M is a product of
closed forms: e^{-s a0} (the minimum age), the uniform age within a beacon interval, the geometric
(independent loss) or Gilbert-Elliott (bursty loss) number of intervals since the last delivery, and
the uniform jitter. Its derivatives come from Cauchy's integral on a small circle (exact to rounding).
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass, replace
from typing import TYPE_CHECKING, Callable

import numpy as np

from orchestrator.analysis.chain_model import chain_model
from orchestrator.analysis.loop_moments import loop_lines
from orchestrator.analysis.sampled_chain import exact_lines

if TYPE_CHECKING:
    from orchestrator.analysis.chain_model import ChainModel
    from orchestrator.scenario.config import Config, Simulation

SPEED_LAWS = ("paper", "acc", "cacc")

# A gain above 1 by less than this is 1: |G| is computed to ~1e-15, and |G(0)| = 1 exactly for every
# law. Near the boundary |G|^2 = 1 + c w^2 at low w; from the grid's 1e-4 rad/s, c > 1e-4 is caught.
GAIN_TOLERANCE = 1e-12


def _hold(s: np.ndarray, period: float) -> np.ndarray:
    """E[e^{-sU}] for U uniform on [0, period): (1 - e^{-s period}) / (s period), 1 at period 0."""
    if period == 0.0:
        return np.ones_like(s)
    x = s * period
    small = np.abs(x) < 1e-8
    safe = np.where(small, 1.0, x)
    return np.where(small, 1.0 - x / 2.0, -np.expm1(-safe) / safe)


@dataclass(frozen=True)
class Channel:
    """How a receiver sees one sender's signal: the age of the sample in use, and how it is used.

    ``min_age`` a0 (s; negative under Gauss-Seidel for a sender that already stepped), ``period`` T (s
    between samples), ``loss`` (probability a sample is lost), ``burst`` (mean loss run, > 1:
    Gilbert-Elliott), ``jitter`` (s, uniform extra age), ``order`` m of the receiver's extrapolation
    (0: hold).
    """

    min_age: float
    period: float
    order: int = 0
    loss: float = 0.0
    burst: float = 1.0
    jitter: float = 0.0

    def age_transform(self, s: np.ndarray) -> np.ndarray:
        """M(s) = E[e^{-sA}] for complex s (the Laplace transform of the age's distribution)."""
        z = np.exp(-s * self.period)
        p = self.loss
        if p == 0.0:
            intervals = np.ones_like(s)
        elif self.burst <= 1.0:  # independent losses: K intervals since the last delivery, P(K > j) = p^j
            intervals = (1.0 - p) / (1.0 - p * z)
        else:  # Gilbert-Elliott: after a delivery, lost with q, then each next one lost with 1 - r
            r = 1.0 / self.burst
            q = p * r / (1.0 - p)
            intervals = (1.0 + q * z / (1.0 - (1.0 - r) * z)) / (1.0 + q / r)
        return np.exp(-s * self.min_age) * _hold(s, self.period) * intervals * _hold(s, self.jitter)

    def _radius(self) -> float:
        """A circle radius for Cauchy's formula well inside M's analytic region (its poles, with losses,
        sit at Re s = ln(p)/T, or ln(1 - r)/T) and small against 1/age (e^{r a} stays near 1)."""
        longest = abs(self.min_age) + self.period + self.jitter
        radius = 0.5 / max(longest, 1e-3)
        if self.loss > 0.0:
            worst = self.loss if self.burst <= 1.0 else 1.0 - 1.0 / self.burst
            if worst > 0.0:
                radius = min(radius, 0.25 * -math.log(worst) / self.period)
        return radius

    def response(self, w: np.ndarray) -> np.ndarray:
        """P(jw): what the receiver sees of a unit sinusoid of frequency w sent through this channel."""
        s = 1j * np.asarray(w, dtype=float)
        if self.order == 0:
            return self.age_transform(s)
        radius, points = self._radius(), 32
        angles = 2.0 * math.pi * np.arange(points) / points
        ring = radius * np.exp(1j * angles)
        values = self.age_transform(s[..., None] + ring)  # M on a circle around each s
        total = np.zeros_like(s)
        for k in range(self.order + 1):
            # Cauchy: M^(k)(s) = k!/(N r^k) sum_n M(s + r e^{i phi_n}) e^{-i k phi_n}; term (-s)^k M^(k)/k!
            derivative_over_factorial = (values * np.exp(-1j * k * angles)).mean(axis=-1) / radius**k
            total = total + (-s) ** k * derivative_over_factorial
        return total


PERFECT = Channel(0.0, 0.0)

# The frequencies every peak search starts from (rad/s): 2000 points, log-spaced over seven decades.
BASE_GRID = np.geomspace(1e-4, 1e3, 2000)


@functools.lru_cache(maxsize=64)
def _base_response(channel: Channel) -> np.ndarray:
    """P(jw) on BASE_GRID, computed once per channel (a time-gap bisection reuses it)."""
    return channel.response(BASE_GRID)


def _response(channel: Channel, w: np.ndarray) -> np.ndarray:
    return _base_response(channel) if w is BASE_GRID else channel.response(w)


@dataclass(frozen=True)
class Chain:
    """One link of the speed chain, linearized about the steady state (kinematic vehicles).

    ``alpha`` = cos(asin(d*/2R)) on a circle (the gap's rate per unit speed difference), 1 on a line.
    ``forward``: the follower's speed and gap as the vehicle ahead sees them (the paper's law);
    ``backward``: the predecessor's communicated speed (cacc), or, under the paper's law, the vehicle
    ahead's position as the follower sees it when it computes the gap it sends; ``sensor``: the predecessor's position as
    the on-board sensor sees it (acc, cacc; a direct wire, only the co-simulation's step).
    """

    law: str
    k_v: float
    alpha: float = 1.0
    speed: float = 25.0  # V_c
    d_star: float = 75.0
    time_gap: float = 1.0  # h (acc, cacc)
    cacc_gain: float = 0.2  # k_p (cacc)
    forward: Channel = PERFECT
    backward: Channel = PERFECT
    sensor: Channel = PERFECT

    @property
    def direction(self) -> str:
        """Which way a fluctuation travels: toward the front (paper) or toward the back (acc, cacc)."""
        return "forward" if self.law == "paper" else "backward"

    def _parts(self, w: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(numerator, denominator) of G(jw); the denominator is the vehicle's own loop."""
        s = 1j * np.asarray(w, dtype=float)
        if self.law == "paper":
            # V_i (s^2 + k_v s + k F Q) = F (k_v s + k) V_(i+1), k = k_v V_c alpha/d*: the follower's speed
            # and gap both come through the forward link F, and the gap it sends is the distance to vehicle
            # i as the follower sees it, through its backward link (Q: that link for a position), so both
            # links are inside vehicle i's loop
            k = self.k_v * self.speed * self.alpha / self.d_star
            p = _response(self.forward, w)
            return p * (self.k_v * s + k), s * s + self.k_v * s + k * p * _response(self.backward, w)
        sensed = _response(self.sensor, w)
        h = self.time_gap
        if self.law == "acc":
            # V_cmd = (d - r)/h, d' = alpha (V_(i-1) - V_i): G = k_v alpha S / (h s^2 + k_v h s + k_v alpha)
            return self.k_v * self.alpha * sensed, h * s * s + self.k_v * h * s + self.k_v * self.alpha
        if self.law == "cacc":
            # V_i' = a = (V_(i-1)^comm - V_i + k_p (d - r - h V_i))/h (the speed loop realises a exactly):
            # G = (s B + k_p alpha S) / (h s^2 + (1 + k_p h) s + k_p alpha); k_v drops out
            kp = self.cacc_gain
            return (s * _response(self.backward, w) + kp * self.alpha * sensed,
                    h * s * s + (1.0 + kp * h) * s + kp * self.alpha)
        raise ValueError(f"unknown speed law {self.law!r}; expected one of {', '.join(SPEED_LAWS)}")

    def transfer(self, w: np.ndarray) -> np.ndarray:
        """G(jw) = V_next / V_previous along the direction the fluctuation travels."""
        numerator, denominator = self._parts(w)
        return numerator / denominator

    def loop_unstable_roots(self) -> int:
        """Roots of the vehicle's own loop (G's denominator, degree 2 in s) in the right half plane.

        By the argument principle: a quasi-polynomial of degree 2 whose s^2 dominates at high frequency
        has Z = 1 - (change of its phase from w = 0 to infinity)/pi roots with Re s > 0. Only the paper's
        law has a delay in its loop (the forward link); acc's and cacc's loops are plain polynomials.
        """
        if self.law == "acc":
            return int(np.sum(np.roots([self.time_gap, self.k_v * self.time_gap, self.k_v * self.alpha]).real > 0))
        if self.law == "cacc":
            coefficients = [self.time_gap, 1.0 + self.cacc_gain * self.time_gap, self.cacc_gain * self.alpha]
            return int(np.sum(np.roots(coefficients).real > 0))
        latest = sum(abs(c.min_age) + c.period * (1 + 30 * c.loss) + c.jitter for c in (self.forward, self.backward))
        k = self.k_v * self.speed * self.alpha / self.d_star
        top = 20.0 * (1.0 + self.k_v + math.sqrt(k) + k * latest)
        # fine enough that e^{-jw a} turns by at most 0.05 rad between two points
        count = int(min(200_000, 2_000 + 20.0 * top * latest))
        w = np.linspace(0.0, top, count)
        phase = np.unwrap(np.angle(self._parts(w)[1]))
        return int(round(1.0 - (phase[-1] - phase[0]) / math.pi))


@dataclass(frozen=True)
class Peak:
    gain: float  # max over w of |G(jw)|
    frequency: float  # rad/s where it is reached (0: the supremum is the limit w -> 0, |G(0)| = 1)
    unstable_roots: int  # of the vehicle's own loop; > 0: the platoon itself is unstable

    @property
    def string_stable(self) -> bool:
        return self.unstable_roots == 0 and self.gain <= 1.0 + GAIN_TOLERANCE


def peak_gain(chain: Chain) -> Peak:
    """The largest |G(jw)| over BASE_GRID, refined twice around the best point (each time a 200-point
    grid over its two neighbours' span)."""
    w = BASE_GRID
    for _ in range(3):
        gain = np.abs(chain.transfer(w))
        best = int(np.argmax(gain))
        if best == 0 and gain[0] <= 1.0 + GAIN_TOLERANCE:
            return Peak(1.0, 0.0, chain.loop_unstable_roots())  # |G| <= 1 everywhere: sup is |G(0)| = 1
        left, right = w[max(best - 1, 0)], w[min(best + 1, len(w) - 1)]
        top_w, top_gain = w[best], gain[best]
        w = np.linspace(left, right, 201)
    return Peak(float(top_gain), float(top_w), chain.loop_unstable_roots())


def _bisect(stable: Callable[[float], bool], low: float, high: float, steps: int) -> float:
    """The boundary between ``stable(low) != stable(high)`` to (high - low) 2^-steps."""
    side = stable(low)
    for _ in range(steps):
        middle = 0.5 * (low + high)
        if stable(middle) == side:
            low = middle
        else:
            high = middle
    return 0.5 * (low + high)


def smallest_time_gap(chain: Chain, longest: float = 100.0) -> float | None:
    """The smallest time gap h (s) that makes this chain string stable, the rest kept; None if none up
    to ``longest``. For acc (ideal sensor) it is 2 alpha/k_v; for cacc it grows with the delay."""
    if not peak_gain(replace(chain, time_gap=longest)).string_stable:
        return None
    if peak_gain(replace(chain, time_gap=1e-3)).string_stable:
        return 1e-3
    return _bisect(lambda h: peak_gain(replace(chain, time_gap=h)).string_stable, 1e-3, longest, 24)


def largest_delay(chain: Chain, with_delay: Callable[[float], Chain], longest: float = 10.0) -> float | None:
    """The largest added delay (s) that keeps the chain string stable (``with_delay(d)``: the chain with
    delay d on its links); None if the chain is not string stable even without one, ``longest`` if it
    is up to there."""
    if not peak_gain(with_delay(0.0)).string_stable:
        return None
    if peak_gain(with_delay(longest)).string_stable:
        return longest
    return _bisect(lambda d: peak_gain(with_delay(d)).string_stable, 0.0, longest, 20)


# --- from a config ------------------------------------------------------------------------------


def _grid(delay: float, step: float) -> float:
    """A link delivers at the end of the step in which its message arrives: the delay on the step grid."""
    return math.ceil(delay / step - 1e-9) * step


def message_channel(config: "Config", direction: str, vehicle: int, order: int) -> Channel:
    """How vehicle messages of ``direction`` reach their receiver: the co-simulation's step, and the
    link of ``vehicle`` (resolved as the run resolves it) when it is not perfect.

    Minimum age a0 of the message in use (the receiver's time minus its output_time), from the wiring
    (orchestrator/execution/python_master.py; the Link steps right after its sender):

    - no Link component: Jacobi a0 = 0 (outputs at t used over [t, t + h)); Gauss-Seidel front to back
      a0 = -h backward (the sender ahead already stepped to t + h), 0 forward;
    - a Link with delay d (delivered at the end of the step in which it arrives, grid(d) = ceil(d/h) h):
      Jacobi a0 = max(h, grid(d)) (one more hop: sender -> link -> receiver); Gauss-Seidel a0 =
      grid(d) - h backward, grid(d) forward.

    Samples are renewed every max(period, h); losses, bursts and jitter as the link draws them.
    """
    step = config.simulation.step
    link = config.resolve_link(direction, vehicle)
    if link.perfect:
        return Channel(minimum_age(config.simulation, direction, None), step, order)
    return Channel(minimum_age(config.simulation, direction, link.delay), max(link.period, step), order, link.loss,
                   link.burst, link.jitter)


def minimum_age(sim: "Simulation", direction: str, delay: float | None) -> float:
    """a0 of ``message_channel``: ``delay`` None for a plain connection (no Link component)."""
    step, gauss_seidel = sim.step, sim.master == "gauss-seidel"
    if delay is None:
        return -step if gauss_seidel and direction == "backward" else 0.0
    grid = _grid(delay, step)
    if gauss_seidel:
        return grid - step if direction == "backward" else grid
    return max(step, grid)


def chain_of(config: "Config", vehicle: int = 2, ideal: bool = False) -> Chain:
    """The speed chain of ``config`` at ``vehicle`` (its law, its links; kinematic vehicles).

    The chain is analysed as homogeneous: every link as ``vehicle``'s (the paper's law: the forward
    link of ``vehicle`` into vehicle - 1; acc, cacc: ``vehicle``'s backward link and sensor).
    ``ideal``: continuous time, no co-simulation step and no link (every channel PERFECT).
    """
    p = config.platoon
    alpha = math.sqrt(1.0 - (p.d_star / (2.0 * config.path.radius)) ** 2) if config.path.kind == "circle" else 1.0
    extrapolate = config.simulation.coupling == "extrapolate"
    vehicle = min(max(vehicle, 1), p.count)
    law = config.speed_law_of(vehicle)
    k_v = config.override(vehicle).k_v or p.k_v
    # The receiver extrapolates the follower's speed and gap, and the target's speed, linearly (order 1),
    # and the sensed position along an arc with the speed rate (order 2); "hold" uses the sample as is.
    forward = message_channel(config, "forward", vehicle, 1 if extrapolate else 0)
    position = law == "paper"  # the paper's law uses the backward message's position (arc, order 2)
    backward = message_channel(config, "backward", vehicle, (2 if position else 1) if extrapolate else 0)
    step = config.simulation.step
    sensor = Channel(-step if config.simulation.master == "gauss-seidel" else 0.0, step, 2 if extrapolate else 0)
    if ideal:
        forward = backward = sensor = PERFECT
    return Chain(law, k_v, alpha, p.speed, p.d_star, p.time_gap, p.cacc_gain, forward, backward, sensor)


def _describe(channel: Channel, what: str) -> str:
    loss = ""
    if channel.loss:
        kind = "independent" if channel.burst <= 1.0 else f"Gilbert-Elliott, mean burst {channel.burst:g}"
        loss = f", {100 * channel.loss:g} % lost ({kind})"
    jitter = f", jitter up to {channel.jitter:g} s" if channel.jitter else ""
    use = {0: "held", 1: "extrapolated linearly (order 1)", 2: "extrapolated along an arc (order 2)"}[channel.order]
    return f"  {what}: age >= {channel.min_age:g} s, renewed every {channel.period:g} s{loss}{jitter}, {use}"


def _law_lines(chain: Chain) -> list[str]:
    if chain.law == "paper":
        k = chain.k_v * chain.speed * chain.alpha / chain.d_star
        return [f"  G(s) = F(s) (k_v s + k) / (s^2 + k_v s + k F(s) Q(s)), k = k_v V_c alpha/d* = {k:.6g} 1/s^2; "
                "F: the follower's speed and gap through the forward link, Q: this vehicle's position through "
                "the follower's backward link (the gap the follower sends)",
                _describe(chain.forward, "F (forward)"), _describe(chain.backward, "Q (backward)")]
    if chain.law == "acc":
        return ["  G(s) = k_v alpha S(s) / (h s^2 + k_v h s + k_v alpha); S: the sensed position (no communication)",
                _describe(chain.sensor, "S (sensor)")]
    return ["  G(s) = (s B(s) + k_p alpha S(s)) / (h s^2 + (1 + k_p h) s + k_p alpha) (k_v does not enter); "
            "B: the communicated speed, S: the sensed position",
            _describe(chain.backward, "B (backward)"), _describe(chain.sensor, "S (sensor)")]


def _condition_lines(config: "Config", chain: Chain) -> list[str]:
    """Where the chain is string stable: the smallest time gap (acc, cacc), the largest link delay (cacc)."""
    if chain.law == "paper":
        return ["  (phase-averaged) above 1 at low frequency for any k_v (|G|^2 > 1 for w^2 < 2k without links): the paper's constant "
                "spacing is never string stable; a link only raises the peak"]
    if chain.law == "acc":
        h_min = smallest_time_gap(chain)
        return [f"  (phase-averaged) string stable for time_gap >= {h_min:.4g} s (with an ideal sensor 2 alpha/k_v = "
                f"{2 * chain.alpha / chain.k_v:.4g} s); acc communicates nothing, so link delays and losses do not enter"]
    h_min = smallest_time_gap(chain)
    lines = [f"  (phase-averaged) string stable for time_gap >= {h_min:.4g} s with these links" if h_min is not None
             else "  (phase-averaged) not string stable for any time_gap up to 100 s with these links"]

    def with_delay(delay: float) -> Chain:
        return replace(chain, backward=replace(chain.backward, min_age=minimum_age(config.simulation, "backward", delay)))

    most = largest_delay(chain, with_delay)
    if most is None:
        lines.append(f"  (phase-averaged) with time_gap = {chain.time_gap:g} s not string stable even without a link delay")
    else:
        lines.append(f"  (phase-averaged) with time_gap = {chain.time_gap:g} s string stable for backward link delays up to "
                     f"{most:.4g} s (on the {config.simulation.step:g} s step grid)")
    return lines


def _delayed(config: "Config") -> Callable[[float], "ChainModel"]:
    """d -> the chain of ``config`` with every link's delay d (the cascade's scan of the delay)."""
    def with_delay(delay: float) -> "ChainModel":
        return chain_model(config.model_copy(update={"links": config.links.model_copy(update={"delay": delay})}))

    return with_delay


def chain_report(config: "Config", sampled: "ChainModel | None" = None) -> str:
    """`platoon analyze`'s string-stability section: G(s), its peak, the conditions; then the sampled-data
    cascade and the vehicle's own loop of ``sampled`` (the config's ``chain_model``, built here if not given)."""
    sampled = sampled or chain_model(config)
    chain = chain_of(config)
    n = config.platoon.count
    arrow = "vehicle i+1 to vehicle i" if chain.direction == "forward" else "vehicle i-1 to vehicle i"
    lines = [f"string stability in closed form (docs/model.md, section 12): {chain.law} law, k_v = {chain.k_v:g} 1/s, "
             f"alpha = {chain.alpha:.6g}" + (f", time_gap = {chain.time_gap:g} s" if chain.law != "paper" else "")
             + (f", cacc_gain = {chain.cacc_gain:g} 1/s" if chain.law == "cacc" else "")
             + f", {config.simulation.master}, {config.simulation.coupling}, step {config.simulation.step:g} s"]
    lines += _law_lines(chain)
    peak = peak_gain(chain)
    exact = sampled.missing is None
    if peak.unstable_roots and not exact:
        lines.append(f"  the vehicle's own loop has {peak.unstable_roots} root(s) in the right half plane: the platoon "
                     "itself is unstable (a link delay inside the paper's loop), string stability is moot")
    # with the cascade beside it, the averaged verdict leaves out the loop's roots: the averaged model of
    # extrapolated samples grows without bound at high frequency, where it counts roots no run shows
    stable = peak.gain <= 1.0 + GAIN_TOLERANCE if exact else peak.string_stable
    verdict = "string stable" if stable else "NOT string stable"
    where = f"at {peak.frequency:.4g} rad/s" if peak.frequency > 0 else "as w -> 0 (|G(jw)| <= 1 everywhere)"
    links = f"; over this platoon's {n - 1} link(s) up to {peak.gain ** (n - 1):.3g}" if n > 1 else ""
    lines.append(f"  peak |G(jw)| = {peak.gain:.4f} {where}, {arrow}: {verdict}{links} (phase-averaged)")
    vehicle = interior_vehicle(config)
    if not exact:
        return "\n".join(lines + _condition_lines(config, chain) + exact_lines(sampled, vehicle, _delayed(config)))
    # the cascade's bounds are the runs' (the averaged ones leave out the aliases the beacons fold back, and
    # are optimistic for extrapolated links: a cacc case, 0.46 s averaged against 0.38 s by the cascade and runs)
    lines += exact_lines(sampled, vehicle, _delayed(config)) + loop_lines(sampled, vehicle)
    if chain.law != "paper":
        lines.append("  for comparison only, the phase-averaged model's bounds (not the runs'; the cascade's above are):")
        lines += [f"  {line}" for line in _condition_lines(config, chain)]
    return "\n".join(lines)


def interior_vehicle(config: "Config") -> int:
    """A receiver inside the string, whose links are the chain's (the paper's law: vehicle 1, fed through
    vehicle 2's links, as ``chain_of(config, 2)``; acc, cacc: vehicle 2)."""
    n = config.platoon.count
    return 1 if config.speed_law_of(min(2, n)) == "paper" and n > 1 else min(2, n)
