"""The speed chain as the sampled-data analyses read it: one description of a config's vehicles, links and laws.

The cascade (``sampled_chain``: the periodic steady state, lifted over the beacon period), the vehicle's own
loop (``loop_moments``: its radius per period) and a run's scatter (``run_scatter``: the string stepped in
time) model the same chain. ``chain_model`` reads it from the config once, and they read only this:

- a **link** (``Timing``) is when its receiver's sample of the sender is taken and how it is lost: the lag
  a0/h and beacon period n = T/h in steps of the Jacobi master, the loss and its mean burst. A plain
  connection (a perfect link, the on-board sensor) is ``PLAIN``;
- a **vehicle** (``Vehicle``) is its speed law linearized on a line (``Vehicle.loop``: its state's flow and
  the gains on dV_s/dt of what it reads), with the links its law reads through;
- the **pushes** are the config's disturbances, the chain's drive.

``missing`` says what the lifting leaves out of this config (None where it is exact: a line, kinematic
vehicles, the Jacobi master, no jitter, beacon periods that are whole multiples of the step). A new link
model (jitter, say) is a field of ``Timing`` and its ``weights``; a new law a branch of ``Vehicle.loop`` and
of ``vehicle_of``. Pure computation (numpy), no I/O.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    from orchestrator.scenario.config import Config

DIRECTIONS = ("backward", "forward")
_TAIL = 1e-15  # loss weights are summed until what is left is below this


def loss_weights(loss: float, burst: float) -> tuple[float, ...]:
    """P(the newest delivered beacon is j beacons old), j = 0, 1, ...: geometric for independent losses;
    for Gilbert-Elliott with mean burst b the renewal law of ``string_stability.Channel`` (the first
    beacon back lost with q = p r/(1 - p), each one before with 1 - r, r = 1/b)."""
    if loss <= 0.0:
        return (1.0,)
    if burst <= 1.0:
        first, ratio = 1.0 - loss, loss
        head: list[float] = []
    else:
        r = 1.0 / burst
        q = loss * r / (1.0 - loss)
        norm = 1.0 + q / r
        head, first, ratio = [1.0 / norm], q / norm, 1.0 - r
    weights, term = list(head), first
    while term > _TAIL or len(weights) < 2:
        weights.append(term)
        term *= ratio
    return tuple(weights)


@dataclass(frozen=True)
class Timing:
    """When a receiver's sample of a sender is taken and how it is used (steps of h).

    ``lag`` a0/h (0 for a plain connection), ``every`` n = T/h (beacon period in steps), ``loss`` the
    probability a beacon is lost and ``burst`` the mean run of losses (1: independent; 1 wherever ``loss``
    is 0, so that links that lose alike are equal)."""

    lag: int
    every: int
    loss: float = 0.0
    burst: float = 1.0

    @functools.cached_property
    def weights(self) -> tuple[float, ...]:
        """The probabilities that the beacon in use is the newest deliverable one, the one before, ...
        (1.0 alone without losses): ``loss_weights``."""
        return loss_weights(self.loss, self.burst)

    @property
    def bursty(self) -> bool:
        """Whether a beacon's loss depends on the one before's (Gilbert-Elliott)."""
        return self.loss > 0.0 and self.burst > 1.0


PLAIN = Timing(0, 1)


@dataclass(frozen=True)
class Vehicle:
    """One vehicle of the chain, linearized on a line.

    ``law``: paper, acc, cacc; ``last``: the paper law's last vehicle (commands V_c); ``c`` = V_c/d*
    (paper); ``time_gap``, ``cacc_gain`` (acc, cacc); ``extrapolate``: the coupling mode; ``sensor``,
    ``comm``: the timing of the sensed position (acc, cacc) and of the communicated message (cacc: the
    backward link; paper: the forward link its follower's speed and gap come through); ``gap_link``:
    the paper's law only, the follower's own backward link, through which the follower sees this vehicle
    when it computes the gap it sends."""

    law: str
    k_v: float
    time_gap: float = 1.0
    cacc_gain: float = 0.2
    c: float = 0.0
    last: bool = False
    extrapolate: bool = True
    sensor: Timing = PLAIN
    comm: Timing = PLAIN
    gap_link: Timing = PLAIN

    def loop(self) -> tuple[np.ndarray, dict[str, float], np.ndarray]:
        """(A, the input gains on dV_s/dt, the push's vector): x' = V_s + p, V_s' = A[1] s + inputs."""
        h, k_v = self.time_gap, self.k_v
        if self.law == "acc":
            return np.array([[0.0, 1.0], [-k_v / h, -k_v]]), {"sensor": k_v / h}, np.array([1.0, 0.0])
        if self.law == "cacc":
            kp = self.cacc_gain
            damping = (1.0 + kp * h) / h
            return (np.array([[0.0, 1.0], [-kp / h, -damping]]), {"sensor": kp / h, "speed": 1.0 / h},
                    np.array([1.0, -damping]))
        gains = {} if self.last else {"speed": k_v, "gap": -k_v * self.c}
        return np.array([[0.0, 1.0], [0.0, -k_v]]), gains, np.array([1.0, 0.0])


@dataclass(frozen=True)
class Push:
    """One of the config's disturbances as the chain is driven by it: a ``kind`` ("speed": a sinusoid of
    ``value`` and ``frequency`` rad/s added to vehicle ``vehicle``'s speed, 0 the virtual target) from ``start``."""

    kind: str
    vehicle: int
    frequency: float
    value: float
    start: float


@dataclass(frozen=True)
class ChainModel:
    """A config's speed chain (module docstring): ``vehicles[i - 1]`` is vehicle i, ``links[(direction, i)]``
    vehicle i's link of that direction (every one of the config's, whether a law reads it or not: they all
    set the beacon grid); the step, the coupling, V_c, the pushes and what the lifting leaves out."""

    step: float
    extrapolate: bool
    speed: float
    vehicles: tuple[Vehicle, ...]
    links: dict[tuple[str, int], Timing]
    pushes: tuple[Push, ...]
    missing: str | None

    @property
    def count(self) -> int:
        return len(self.vehicles)

    def vehicle(self, index: int) -> Vehicle:
        return self.vehicles[index - 1]

    def law(self, index: int) -> str:
        return self.vehicles[index - 1].law

    def lifting_period(self, record_every: int = 1) -> int:
        """P: the steps after which the beacons of every link (and the records) repeat."""
        return math.lcm(record_every, *(timing.every for timing in self.links.values()))

    @property
    def bursty(self) -> bool:
        """Whether any link loses beacons in bursts (no moment over the losses models that)."""
        return any(timing.bursty for timing in self.links.values())


def exact_applies(config: "Config") -> str | None:
    """None when the lifting models this config's co-simulation exactly, else what it leaves out."""
    sim, p = config.simulation, config.platoon
    if config.path.kind != "line":
        return "a circle (the lifting is linearized on a straight line)"
    if sim.master != "jacobi":
        return "the Gauss-Seidel master (the lifting follows the Jacobi master's exchange)"
    if any((config.override(i).dynamics or p.dynamics) != "kinematic" for i in range(1, p.count + 1)):
        return "m3pi dynamics (the lifting knows the kinematic vehicle)"
    for i in range(1, p.count + 1):
        for direction in DIRECTIONS:
            link = config.resolve_link(direction, i)
            if link.jitter > 0.0:
                return f"jitter on the {direction} link of vehicle {i}"
            beacons = link.period / sim.step
            if link.period > sim.step and abs(beacons - round(beacons)) > 1e-9:
                return f"the {direction} link of vehicle {i}: period {link.period:g} s is not a multiple of the step"
    return None


def _timing(config: "Config", direction: str, vehicle: int) -> Timing:
    """How the receiver at the end of ``vehicle``'s ``direction`` link samples its sender (Jacobi)."""
    link, step = config.resolve_link(direction, vehicle), config.simulation.step
    if link.perfect:
        return PLAIN
    lag = max(1, math.ceil(link.delay / step - 1e-9))
    every = max(1, round(link.period / step))
    return Timing(lag, every, link.loss, link.burst if link.loss > 0.0 and link.burst > 1.0 else 1.0)


def vehicle_of(config: "Config", index: int, links: dict[tuple[str, int], Timing]) -> Vehicle:
    """Vehicle ``index`` of the config as a receiver of the speed chain, reading through ``links``."""
    p, n = config.platoon, config.platoon.count
    law = config.speed_law_of(index)
    k_v = config.override(index).k_v or p.k_v
    extrapolate = config.simulation.coupling == "extrapolate"
    # only what the law reads (the rest at its default): vehicles that differ only in what their law ignores
    # (acc's link, the paper law's time gap) are equal, and share the cascade's and the loop's remembered results
    if law == "paper":
        if index == n:
            return Vehicle(law, k_v, c=p.speed / p.d_star, last=True, extrapolate=extrapolate)
        return Vehicle(law, k_v, c=p.speed / p.d_star, extrapolate=extrapolate,
                       comm=links[("forward", index + 1)], gap_link=links[("backward", index + 1)])
    if law == "acc":
        return Vehicle(law, k_v, p.time_gap, extrapolate=extrapolate)
    return Vehicle(law, k_v=1.0, time_gap=p.time_gap, cacc_gain=p.cacc_gain, extrapolate=extrapolate,  # no k_v in cacc
                   comm=links[("backward", index)])


def chain_model(config: "Config") -> ChainModel:
    """The config's chain (``ChainModel``): the one place the sampled-data analyses read a config's vehicles,
    links and laws."""
    count = config.platoon.count
    links = {(direction, i): _timing(config, direction, i) for i in range(1, count + 1) for direction in DIRECTIONS}
    vehicles = tuple(vehicle_of(config, i, links) for i in range(1, count + 1))
    pushes = tuple(Push(d.kind, d.vehicle, d.frequency, d.value, d.start) for d in config.disturbance)
    return ChainModel(config.simulation.step, config.simulation.coupling == "extrapolate", config.platoon.speed,
                      vehicles, links, pushes, exact_applies(config))
