"""A single run's headline (orchestrator/analysis/headline.py): its growth per link at the probes, the standard
error that lets its verdict stand, and the probes too weak to judge, on signals whose answer is known."""

from __future__ import annotations

import math

import numpy as np
import pytest

from orchestrator.analysis.headline import Mixing, measured_headline

PROBES = [0.1, 0.3, 1.0, 3.0]
PERIOD = 2 * math.pi / 0.1
WINDOW = (0.0, 4 * PERIOD)  # four whole periods of the lowest probe, as the study fits
T = np.arange(0.0, WINDOW[1] + 1e-9, 0.1)
NAMES = [f"vehicle{k}" for k in (4, 3, 2, 1)]


def errors(gains: list[float], first: list[float], noise: float = 0.0, gap_noise: float = 0.0,
           seed: int = 0) -> dict[str, dict[str, np.ndarray]]:
    """Speed errors along NAMES: each probe k at amplitude first[k] * gains[k]**link, plus white noise."""
    rng = np.random.default_rng(seed)
    out = {}
    for link, name in enumerate(NAMES):
        speed = sum(a * g**link * np.sin(w * T + link) for a, g, w in zip(first, gains, PROBES))
        out[name] = {"t": T, "speed": speed + noise * rng.standard_normal(len(T)),
                     "gap": gap_noise * rng.standard_normal(len(T))}
    return out


def test_a_clean_run_is_judged_and_its_scatter_is_rounding() -> None:
    headline = measured_headline(errors([0.99, 0.98, 0.9, 0.5], [0.03, 0.01, 0.003, 0.01]), NAMES, PROBES, WINDOW,
                                 PERIOD, None)
    assert headline.growth == pytest.approx(0.99, rel=1e-9) and headline.frequency == 0.1
    assert headline.periods == 4 and headline.sigma < 1e-9
    assert headline.verdict == "does not grow" and not headline.weak


def test_a_noisy_run_near_one_is_inside_the_noise_and_far_from_it_is_not() -> None:
    """Noise of 0.005 m/s on 0.01 m/s probes: a 1.01 growth is inside three standard errors, 1.3 is not."""
    near = [measured_headline(errors([1.01, 0.9, 0.8, 0.5], [0.01] * 4, noise=0.005, seed=s), NAMES, PROBES,
                              WINDOW, PERIOD, None) for s in range(5)]
    assert all(h.verdict == "inside the noise" for h in near), [h.text() for h in near]
    far = measured_headline(errors([1.3, 0.9, 0.8, 0.5], [0.01] * 4, noise=0.005), NAMES, PROBES, WINDOW, PERIOD, None)
    assert far.verdict == "grows" and far.sigma > 0 and abs(far.growth - 1.3) < 5 * far.sigma


def test_the_standard_error_is_the_scatter_over_runs() -> None:
    """Over 40 noisy runs of one signal, the headlines scatter as their own standard errors say (to 40 %:
    four periods give each standard error from three degrees of freedom)."""
    runs = [measured_headline(errors([1.05, 0.9, 0.8, 0.5], [0.01] * 4, noise=0.003, seed=s), NAMES, PROBES, WINDOW,
                              PERIOD, None) for s in range(40)]
    spread = float(np.std([h.growth for h in runs], ddof=1))
    typical = float(np.sqrt(np.mean([h.sigma**2 for h in runs])))
    assert spread == pytest.approx(typical, rel=0.4)


def test_weak_probes_are_flagged_not_judged() -> None:
    """3 rad/s falls to 1e-11 m/s at the end of the stretch: below the numerical floor, left out even though
    it 'grows'; with 2 m of gap noise, the paper law's mixing floor takes the 1 rad/s probe at 3e-4 m/s (no two
    probes sum to 1 rad/s: the third order, 25 (2/75)^3 = 4.7e-4 m/s) but not the 0.03 m/s one."""
    weak = measured_headline(errors([0.99, 0.98, 0.9, 1.2], [0.03, 0.01, 0.003, 5e-12]), NAMES, PROBES, WINDOW,
                             PERIOD, None)
    assert set(weak.weak) == {3.0} and "numerical floor" in weak.weak[3.0]
    assert weak.frequency == 0.1 and weak.verdict == "does not grow"
    mixed = measured_headline(errors([0.99, 0.98, 0.9, 0.5], [0.03, 0.01, 3e-4, 0.01], gap_noise=2.0), NAMES, PROBES,
                              WINDOW, PERIOD, Mixing(25.0, {name: 75.0 for name in NAMES}))
    assert 1.0 in mixed.weak and "V d*/d" in mixed.weak[1.0] and 0.1 not in mixed.weak


def test_the_verdict_is_held_to_the_predicted_scatter_where_the_analysis_gives_one():
    """A run 2 % above 1 with a measured standard error of 0.1 % grows by its own batch means, but the analysis
    predicts that one run of its config scatters by 1 %: inside the noise. Without a prediction, the measured."""
    from orchestrator.analysis.headline import Headline

    assert Headline(1.02, 3.0, 0.001, 4).verdict == "grows"
    predicted = Headline(1.02, 3.0, 0.001, 4, predicted=0.01)
    assert predicted.verdict == "inside the noise"
    assert "+- 0.01 (predicted: a run's standard deviation over its losses; measured 0.001" in predicted.text()
    assert Headline(1.04, 3.0, 0.002, 4, predicted=0.01).verdict == "grows"  # 4 predicted sigma out
    # a run that scatters beyond the prediction (it left the linear regime): held to its own, larger scatter
    assert Headline(1.04, 3.0, 0.02, 4, predicted=0.01).verdict == "inside the noise"


def test_measured_headline_takes_the_prediction_of_its_probe():
    t = np.arange(0.0, 4 * 2 * math.pi / 0.5, 0.1)
    errs = {name: {"t": t, "speed": a * np.sin(0.5 * t) + b * np.sin(2.0 * t), "gap": np.zeros_like(t)}
            for name, a, b in (("v1", 1.0, 1.0), ("v2", 1.1, 0.5))}
    headline = measured_headline(errs, ["v1", "v2"], [0.5, 2.0], (0.0, t[-1] + 0.05), 2 * math.pi / 0.5, None,
                                 predicted=[0.03, 0.2])
    assert headline.frequency == 0.5 and headline.predicted == 0.03
