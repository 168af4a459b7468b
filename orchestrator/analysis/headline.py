"""A single run's headline (`platoon stability`, `platoon stability-map`): its growth per link at the probe
frequencies, with the confidence that lets its verdict stand, and the probes too weak to judge.

With losses a run's gain is a random variable: every message's age is a draw, and the run's noise adds to
what each probe measures. The headline's scatter is taken from the run itself, by batch means: the steady
window holds whole periods of the lowest probe (the study's four of 0.1 rad/s), every probe is a whole
number of cycles in each of them, so each period gives the headline's growth again from its own stretch of
noise; their standard deviation over sqrt(periods) is the standard error of the whole window's value (the
fit over the window is, to first order, the mean of the periods' fits). A verdict ("grows", "does not grow")
stands only where |growth - 1| is more than ``CONFIDENCE`` standard deviations from 1: the analysis' own
prediction of a single run's scatter over its delivery patterns where it is given (``run_scatter``: the
driven cascade's second moment), or the measured standard error where that is larger (the run then
scatters beyond what the linear model predicts), else
the measured one; elsewhere the run is "inside the noise". Both are printed. With three or fewer periods
no measured scatter is given.

A probe is **weak**, flagged and left out of the headline, where a vehicle along the stretch carries it
below what can be told from other signals:

- ``NUMERICAL_FLOOR`` (1e-9 m/s): fifty times the residue a settled run of the study still carries
  (2e-11 m/s from 140 s on, docs/model.md section 12), far above rounding at 25 m/s (5e-15);
- under the paper's law, V d*/d is not linear in the gap: its terms of order n carry products of n probes
  onto their sums and differences. A probe that such a sum of two probes reaches gets the second-order term,
  V_c (s/d)^2, every other the third, V_c (s/d)^3, with s the rms of that vehicle's gap error over the
  window and d the equilibrium gap: below it, the probe may be the others' mixing (the held lossy runs,
  metres of gap noise);
- where the analysis predicts it (``run_scatter``), a probe buried in the noise of the losses: a run's growth
  there centres off the cascade's by more than its own standard deviation.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

CONFIDENCE = 3.0  # standard errors between the headline and 1 for a single run's verdict to stand
NUMERICAL_FLOOR = 1e-9  # m/s
MIN_PERIODS = 4  # batch means need a few periods to give a standard deviation


def probe_amplitudes(errors: dict[str, dict[str, np.ndarray]], order: list[str], frequencies: list[float],
                     window: tuple[float, float], kind: str = "speed") -> np.ndarray:
    """Per vehicle along ``order``, per frequency: the amplitude of its ``kind`` error at that frequency (all
    frequencies and an offset fitted jointly by least squares over ``window``); shape (vehicles, frequencies)."""
    fits: dict[str, np.ndarray] = {}
    for name in order:  # vehicles recorded at the same instants share one design: one solve for all of them
        if name in fits:
            continue
        t = errors[name]["t"]
        alike = [other for other in order if other not in fits and np.array_equal(errors[other]["t"], t)]
        inside = (t >= window[0] - 1e-9) & (t <= window[1] + 1e-9)
        columns = [f(w * t[inside]) for w in frequencies for f in (np.cos, np.sin)] + [np.ones(int(inside.sum()))]
        values = np.column_stack([errors[other][kind][inside] for other in alike])
        solved, *_ = np.linalg.lstsq(np.column_stack(columns), values, rcond=None)
        fits.update(zip(alike, solved.T))
    return np.array([[math.hypot(fits[name][2 * k], fits[name][2 * k + 1]) for k in range(len(frequencies))]
                     for name in order])


@dataclass(frozen=True)
class Mixing:
    """What the paper law's V d*/d mixes (module docstring): V_c, and each vehicle's equilibrium gap by name."""

    speed: float
    gaps: dict[str, float]


@dataclass(frozen=True)
class Headline:
    """``growth`` per link (the largest over the judged probes, at ``frequency`` rad/s), its standard
    error ``sigma`` from ``periods`` batch means (None: too few periods), and ``weak``: probe (rad/s) ->
    why it is not judged. ``growth`` is NaN where every probe is weak."""

    growth: float
    frequency: float
    sigma: float | None
    periods: int
    weak: dict[float, str] = field(default_factory=dict)
    predicted: float | None = None  # the analysis' standard deviation of a run's growth there (run_scatter)

    @property
    def confidence_sigma(self) -> float | None:
        """The scatter the verdict is held to: the predicted one where the analysis gives it, or the measured one
        where that is larger (a run that scatters more than the linear model predicts has left its regime), else
        the measured one."""
        if self.predicted is None:
            return self.sigma
        return self.predicted if self.sigma is None else max(self.predicted, self.sigma)

    @property
    def verdict(self) -> str:
        """"grows", "does not grow", "inside the noise", or "no probe to judge"."""
        if math.isnan(self.growth):
            return "no probe to judge"
        sigma = self.confidence_sigma
        if sigma is not None and abs(self.growth - 1.0) <= CONFIDENCE * sigma:
            return "inside the noise"
        return "grows" if self.growth > 1.0 else "does not grow"

    def text(self) -> str:
        spread = (f" +- {self.sigma:.2g} (standard error over {self.periods} periods)" if self.sigma is not None
                  else f" (no scatter: {self.periods} period(s), fewer than {MIN_PERIODS})")
        if self.predicted is not None and not math.isnan(self.growth):
            measured = (f"measured {self.sigma:.2g}, the standard error over {self.periods} periods"
                        if self.sigma is not None else "none measured")
            spread = f" +- {self.predicted:.2g} (predicted: a run's standard deviation over its losses; {measured})"
        where = "" if math.isnan(self.growth) else f" at {self.frequency:g} rad/s"
        weak = "" if not self.weak else "; weak probes, not judged: " + "; ".join(
            f"{w:g} rad/s ({why})" for w, why in sorted(self.weak.items()))
        word = self.verdict
        word = f"this disturbance {word} along the platoon" if word in ("grows", "does not grow") else word.upper()
        return f"{self.growth:.4f}{spread}{where}: {word}{weak}"


def _mixing_floor(mixing: Mixing, errors: dict, order: list[str], frequencies: list[float],
                  window: tuple[float, float]) -> np.ndarray:
    """Per vehicle along ``order``, per probe: what V d*/d's mixing of the other probes may put there (m/s)."""
    reached = [any(math.isclose(w, a + b, rel_tol=1e-9) or math.isclose(w, abs(a - b), rel_tol=1e-9)
                   for a in frequencies for b in frequencies) for w in frequencies]
    floors = []
    for name in order:
        t = errors[name]["t"]
        inside = (t >= window[0] - 1e-9) & (t <= window[1] + 1e-9)
        gap = errors[name]["gap"][inside]
        if name not in mixing.gaps or not np.isfinite(gap).any():  # the target: no gap, no law of its own
            floors.append([0.0] * len(frequencies))
            continue
        relative = float(np.sqrt(np.mean((gap - np.mean(gap)) ** 2))) / mixing.gaps[name]
        floors.append([mixing.speed * relative ** (2 if second else 3) for second in reached])
    return np.array(floors)


def _weak_probes(mixing: Mixing | None, errors: dict, order: list[str], frequencies: list[float],
                 window: tuple[float, float], amplitudes: np.ndarray) -> dict[float, str]:
    weak = {}
    floors = (_mixing_floor(mixing, errors, order, frequencies, window) if mixing is not None
              else np.zeros_like(amplitudes))
    for k, w in enumerate(frequencies):
        lowest = int(np.argmin(amplitudes[:, k]))
        if amplitudes[lowest, k] < NUMERICAL_FLOOR:
            weak[w] = f"{order[lowest]} carries {amplitudes[lowest, k]:.2g} m/s, below the numerical floor {NUMERICAL_FLOOR:g}"
            continue
        under = np.flatnonzero(amplitudes[:, k] < floors[:, k])
        if len(under):
            i = int(under[0])
            weak[w] = (f"{order[i]} carries {amplitudes[i, k]:.2g} m/s, below the {floors[i, k]:.2g} V d*/d may mix "
                       "there from the other probes")
    return weak


def _growths(amplitudes: np.ndarray) -> np.ndarray:
    """Per probe, the growth per link over the stretch: (last amplitude / first) ** (1 / links)."""
    links = len(amplitudes) - 1
    with np.errstate(divide="ignore", invalid="ignore"):
        return (amplitudes[-1] / amplitudes[0]) ** (1.0 / links)


def measured_headline(errors: dict, clean: list[str], frequencies: list[float], window: tuple[float, float],
                      lowest_period: float, mixing: Mixing | None, predicted: list[float] | None = None,
                      buried: dict[float, str] | None = None) -> Headline:
    """The headline of the stretch ``clean`` over ``window`` (whole periods of ``lowest_period`` s);
    ``mixing``: the paper law's (None for acc and cacc, linear in the gap); ``predicted``: per frequency, the
    analysis' standard deviation of a single run's growth (``run_scatter``), which the verdict is held to;
    ``buried``: the probes the analysis predicts a run measures its noise at (``Scatter.buried``), weak too."""
    amplitudes = probe_amplitudes(errors, clean, frequencies, window)
    weak = {**_weak_probes(mixing, errors, clean, frequencies, window, amplitudes), **(buried or {})}
    judged = [k for k, w in enumerate(frequencies) if w not in weak]
    if not judged:
        return Headline(math.nan, math.nan, None, 0, weak)
    growths = _growths(amplitudes)
    best = max(judged, key=lambda k: growths[k])
    periods = int(round((window[1] - window[0]) / lowest_period))
    sigma = None
    if periods >= MIN_PERIODS:
        per_period = [_growths(probe_amplitudes(errors, clean, frequencies, (window[0] + i * lowest_period,
                                                                             window[0] + (i + 1) * lowest_period)))[best]
                      for i in range(periods)]
        sigma = float(np.std(per_period, ddof=1) / math.sqrt(periods))
    return Headline(float(growths[best]), frequencies[best], sigma, periods, weak,
                    None if predicted is None else predicted[best])
