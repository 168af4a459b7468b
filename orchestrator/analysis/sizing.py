"""What an analysis of a config would cost, sized before it starts: what it cannot do is refused in one line.

Every value docs/config.md allows is a valid config, but not every one is an analysis this machine can
do: ``links.period = 3600`` lifts the sampled-data cascade over 180 000 steps (its matrices would take
terabytes), ``links.loss = 0.999999`` with ``links.burst = 1e6`` asks for the ~3e7 beacons a receiver may
still be using; a disturbance that starts after the run ends gives nothing to measure. Each analysis
(``platoon analyze``, ``stability``, ``stability-map``) calls ``check_analysis`` at its entry: it
raises ``AnalysisRefused`` (a ``ConfigError``: one line, naming the key) before any work. The bounds:

* ``LIFTED_BYTES``: the exact cascade's lifted maps (``sampled_chain.receiver_maps``) are (5P)^2 complex
  per frequency, solved at ``COARSE_FREQUENCIES`` at once: about ``BYTES_PER_LIFTED`` x frequencies x
  P^2 bytes at their peak (tracemalloc: 1464 at P = 20, 1401 at P = 30; ``platoon analyze`` lifted over
  P = 50, 1 s beacons on 0.02 s steps, peaked at 399 MB resident in 4.2 s). 768 MiB keeps the whole
  analysis under 2 GiB of address space (``prlimit --as``), and the time (growing as P^3) about a minute.
* ``MAX_LOSS_TERMS``: how many beacons back a lossy receiver may be using before what is left weighs less
  than 1e-15 (``sampled_chain.loss_weights``): about 34.5 / -ln(loss) independent, 34.5 x burst in bursts.
  A hundred thousand keeps its tables (terms x frequencies, complex) at 160 MB.

A link that loses every message (``loss = 1``) is no size problem but no chain either: nothing sent ever
arrives, so its receiver keeps its sender's initial message for the whole run. ``nothing_arrives``
answers that in words, instead of an analysis that divides by the delivered fraction.
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

from orchestrator.scenario.config import ConfigError

if TYPE_CHECKING:
    from orchestrator.analysis.chain_model import ChainModel
    from orchestrator.scenario.config import Config

LIFTED_BYTES = 768 * 2**20
BYTES_PER_LIFTED = 1500  # bytes per frequency per P^2 at the peak (tracemalloc: 1464 at P = 20, 1401 at 30; m is 5P x 5P)
MAX_LOSS_TERMS = 100_000
_TAIL = 1e-15  # as sampled_chain's: loss weights are summed until what is left is below this
DIRECTIONS = ("backward", "forward")


class AnalysisRefused(ConfigError):
    """An analysis this machine cannot do within the bounds above; the text names the key and the numbers."""


def link_key(config: "Config", direction: str, vehicle: int, key: str) -> str:
    """The narrowest table that sets ``key`` of vehicle ``vehicle``'s ``direction`` link, as a user writes it."""
    links = config.links
    own = links.vehicles.get(str(vehicle))
    if own is not None and getattr(getattr(own, direction), key) is not None:
        return f"links.vehicles.{vehicle}.{direction}.{key}"
    if getattr(getattr(links, direction), key) is not None:
        return f"links.{direction}.{key}"
    return f"links.{key}"


def _links(config: "Config"):
    """(direction, vehicle, its settings) of every link the wiring makes."""
    for vehicle in range(1, config.platoon.count + 1):
        for direction in DIRECTIONS:
            yield direction, vehicle, config.resolve_link(direction, vehicle)


def _read(config: "Config", direction: str, vehicle: int) -> bool:
    """Whether the laws read vehicle ``vehicle``'s ``direction`` link: a backward link (the predecessor's
    broadcast) its receiver under the paper's law and cacc; a forward one (the follower's speed and gap) the
    vehicle ahead under the paper's law. acc reads its radar, no link."""
    if direction == "backward":
        return config.speed_law_of(vehicle) in ("paper", "cacc")
    return vehicle > 1 and config.speed_law_of(vehicle - 1) == "paper"


def cut_links(config: "Config") -> list[str]:
    """The keys of the links the laws read that lose every message (``loss = 1``), each named once."""
    keys = [link_key(config, direction, vehicle, "loss") for direction, vehicle, link in _links(config)
            if link.loss >= 1.0 and _read(config, direction, vehicle)]
    return list(dict.fromkeys(keys))


def nothing_arrives(config: "Config") -> str | None:
    """The answer for a platoon whose links lose every message (None if none does)."""
    keys = cut_links(config)
    if not keys:
        return None
    return (f"{', '.join(keys)} = 1: no message sent over the links {'it sets' if len(keys) == 1 else 'they set'} "
            "ever arrives, so each receiver keeps its sender's initial message (t = 0) for the whole run: no "
            "disturbance crosses such a link (its gain is 0) and no vehicle follows through it; there is no chain to "
            "be string stable or not (docs/links.md, Loss)")


def loss_terms(loss: float, burst: float) -> int:
    """How many beacons back ``sampled_chain.loss_weights`` goes for a link losing ``loss`` in bursts of
    ``burst`` (computed, not built: the count alone is what can be too big)."""
    if loss <= 0.0:
        return 1
    if burst <= 1.0:
        first, ratio, head = 1.0 - loss, loss, 0
    else:
        r = 1.0 / burst
        q = loss * r / (1.0 - loss)
        first, ratio, head = q / (1.0 + q / r), 1.0 - r, 1
    if first <= _TAIL:
        return head + 2
    return head + max(2, math.floor(math.log(_TAIL / first) / math.log(ratio)) + 1)  # the terms above _TAIL


def _check_disturbances(config: "Config") -> None:
    stop = config.simulation.stop_time
    for number, disturbance in enumerate(config.disturbance, start=1):
        if disturbance.start >= stop:
            raise AnalysisRefused(f"disturbance {number} (vehicle {disturbance.vehicle}): start = {disturbance.start:g} s "
                                  f"is not before the run's end (simulation.stop_time = {stop:g} s): it never acts, "
                                  "so there is nothing to measure; start it earlier or run longer")


def _check_lifting(config: "Config", chain: "ChainModel") -> None:
    """The exact cascade's size, where it is computed (``chain.missing`` None)."""
    from orchestrator.analysis.sampled_chain import COARSE_FREQUENCIES

    if chain.missing is not None:
        return
    for direction, vehicle, link in _links(config):
        terms = loss_terms(link.loss, link.burst)
        if not link.perfect and terms > MAX_LOSS_TERMS:
            raise AnalysisRefused(
                f"{link_key(config, direction, vehicle, 'loss')} = {link.loss:g} with "
                f"{link_key(config, direction, vehicle, 'burst')} = {link.burst:g}: a receiver may be using any of "
                f"the last {terms:,} beacons, more than the {MAX_LOSS_TERMS:,} the sampled-data cascade sums over "
                "this machine's memory and a minute; lower the loss or the burst")
    period = chain.lifting_period()
    need = BYTES_PER_LIFTED * COARSE_FREQUENCIES * period**2
    if need > LIFTED_BYTES:
        step = config.simulation.step
        direction, vehicle, link = max(_links(config), key=lambda found: found[2].period)
        raise AnalysisRefused(
            f"{link_key(config, direction, vehicle, 'period')} = {link.period:g} s: the sampled-data cascade is "
            f"lifted over {period:,} steps of simulation.step = {step:g} s, about {need / 2**30:,.3g} GiB of "
            f"matrices, more than its bound of {LIFTED_BYTES / 2**30:g} GiB; beacons of at most "
            f"{_longest_period(step):g} s on that step fit")


def _longest_period(step: float) -> float:
    """The longest beacon period (a whole number of steps) whose lifting fits ``LIFTED_BYTES``."""
    from orchestrator.analysis.sampled_chain import COARSE_FREQUENCIES

    return math.isqrt(LIFTED_BYTES // (BYTES_PER_LIFTED * COARSE_FREQUENCIES)) * step


def check_analysis(config: "Config", measured: bool = False, closed_form: bool = True,
                   chain: "ChainModel | None" = None) -> None:
    """Raise ``AnalysisRefused`` for what an analysis of ``config`` cannot do: the closed form's work above its
    bounds (``closed_form``), a measurement (``measured``) of a disturbance that never acts. ``chain``: the
    config's ``chain_model`` where the caller has it."""
    if measured:
        _check_disturbances(config)
    if closed_form and not cut_links(config):  # else answered: nothing to size
        from orchestrator.analysis.chain_model import chain_model

        _check_lifting(config, chain or chain_model(config))
