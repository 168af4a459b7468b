"""The closed form's verdict on a config's string stability: one object from one function, for `platoon
analyze`, `platoon stability` and `platoon stability-map` alike.

The verdict has two parts, and says which model gave each:

- the **cascade's peak**: the largest growth per link far down the string over all frequencies, from the
  sampled-data cascade (``sampled_chain.peak_growth``) where it models the config exactly, else from the
  phase-averaged chain (``string_stability.peak_gain``);
- the **vehicle's own loop**: under the paper's law vehicle i's position comes back to it through its
  follower's two links (``loop_moments``). Where the loop *grows* (its mean over the losses), the platoon
  has no steady state and the cascade's gains are of one never reached: not string stable, whatever the
  peak. Where it *was not computed* (burst losses; more delivery patterns a period than are enumerated)
  the verdict is the cascade's alone and says so, never silently "settles". Acc and cacc have no link in
  the loop (their loops are stable for positive gains); under the phase-averaged model the loop is the
  averaged one's roots.

String stable: the peak at most 1 (to the models' tolerances) and the loop not growing. Pure computation.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import TYPE_CHECKING

from orchestrator.analysis.chain_model import ChainModel, chain_model
from orchestrator.analysis.loop_moments import LoopRadii, loop_radii
from orchestrator.analysis.sampled_chain import GROWTH_TOLERANCE, PeakGrowth, peak_growth
from orchestrator.analysis.string_stability import GAIN_TOLERANCE, chain_of, interior_vehicle, peak_gain

if TYPE_CHECKING:
    from orchestrator.scenario.config import Config

CASCADE, AVERAGED = "sampled-data cascade", "phase-averaged"
SETTLES, GROWS, NO_LOOP, NOT_COMPUTED = "settles", "grows", "no link in the loop", "not computed"


@dataclass(frozen=True)
class LoopState:
    """The vehicle's own loop: ``state`` (SETTLES, GROWS, NO_LOOP, NOT_COMPUTED and ``reason``); the spectral
    radius per lifting period of the mean's map and of the second moment's (None where not computed) and
    that period in s; ``mean_square_grows`` where the mean settles but the rms over the losses grows."""

    state: str
    mean_radius: float | None = None
    mean_square_radius: float | None = None
    period_seconds: float | None = None
    reason: str = ""

    @property
    def mean_square_grows(self) -> bool:
        return self.state == SETTLES and self.mean_square_radius is not None and self.mean_square_radius >= 1.0

    def text(self) -> str:
        if self.state == NOT_COMPUTED:
            return f"its loop through the links not computed ({self.reason}): the verdict is the cascade's alone"
        if self.state == NO_LOOP:
            return "no link inside the vehicle's own loop"
        if self.mean_radius is None:  # the averaged model: roots, no radius
            return "its own loop " + ("GROWS (roots in the right half plane)" if self.state == GROWS else "settles")
        rate = math.log(max(self.mean_radius, 1e-300)) / self.period_seconds
        if self.state == GROWS:
            return f"its own loop through the links GROWS ({rate:+.4g} 1/s): no steady state"
        rms = "" if not self.mean_square_grows else ", though its rms over the losses grows (mean square)"
        return f"its own loop through the links settles ({rate:+.4g} 1/s){rms}"


@dataclass(frozen=True)
class ClosedFormVerdict:
    """The closed form's verdict (module docstring): which model, its peak growth per link and where, the loop."""

    model: str  # CASCADE or AVERAGED
    peak_growth_per_link: float
    peak_frequency: float  # rad/s; 0: the supremum is the limit w -> 0, where every chain passes 1
    loop: LoopState

    @property
    def cascade_stable(self) -> bool:
        tolerance = GROWTH_TOLERANCE if self.model == CASCADE else GAIN_TOLERANCE
        return self.peak_growth_per_link <= 1.0 + tolerance

    @property
    def string_stable(self) -> bool:
        return self.cascade_stable and self.loop.state != GROWS

    def line(self) -> str:
        """The verdict as one line, the same in every command."""
        where = f"at {self.peak_frequency:.4g} rad/s" if self.peak_frequency > 0 else "as w -> 0"
        word = "string stable" if self.string_stable else "NOT string stable"
        return (f"closed form ({self.model}): growth per link far down the string peaks at "
                f"{self.peak_growth_per_link:.4f} {where}; {self.loop.text()}: {word}")


def _loop_state(radii: LoopRadii | None) -> LoopState:
    if radii is None:
        return LoopState(NO_LOOP)
    seconds = radii.period * radii.step
    if math.isnan(radii.mean):
        return LoopState(NOT_COMPUTED, period_seconds=seconds, reason=radii.reason)
    return LoopState(SETTLES if radii.mean_stable else GROWS, radii.mean, radii.mean_square, seconds, radii.reason)


def closed_form_verdict(config: "Config", peak: PeakGrowth | None = None, mean_square: bool = True,
                        chain: ChainModel | None = None) -> ClosedFormVerdict:
    """The verdict for ``config``'s interior vehicle (``string_stability.interior_vehicle``). ``peak``: its
    cascade's peak where the caller computed it already (a map's grid cell: ``peak_growth`` of a chain with
    the same interior vehicle, step and lifting period), else computed here; ``mean_square``: the loop's
    second moment too (the verdict does not need it: up to 1.3 s a loop); ``chain``: the config's
    ``chain_model`` where the caller has it."""
    vehicle = interior_vehicle(config)
    chain = chain or chain_model(config)
    if chain.missing is None:
        peak = peak or peak_growth(chain, vehicle)
        loop = loop_radii(chain, vehicle, mean_square)
        return ClosedFormVerdict(CASCADE, peak.gain, peak.frequency, _loop_state(loop))
    averaged = peak_gain(chain_of(config))
    loop = LoopState(GROWS if averaged.unstable_roots else SETTLES)
    return ClosedFormVerdict(AVERAGED, averaged.gain, averaged.frequency, loop)
