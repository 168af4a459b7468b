"""The linearization about the circular equilibrium, from the same model code the FMUs run."""

from __future__ import annotations

import math

import numpy as np
import pytest

from orchestrator.analysis.linear import jacobian, multiplicity_test, our_families, paper_eigenvalues
from orchestrator.analysis.string_stability import chain_of, peak_gain
from tests.conftest import make_config


@pytest.mark.parametrize("count", [1, 4, 6])
@pytest.mark.parametrize("values", [dict(radius=50.0, d_star=75.0, speed=25.0), dict(radius=1.0, d_star=0.7, speed=0.35)])
def test_sine_platoon_eigenvalues_follow_the_closed_form_families(count, values):
    config = make_config(path={"radius": values["radius"]},
                         platoon={"count": count, "d_star": values["d_star"], "speed": values["speed"]})
    a, residual = jacobian(config)
    assert residual < 1e-9  # x_eq is an equilibrium of the sine law
    assert sum(f.count for f in our_families(config, count)) == 4 * count
    for family in our_families(config, count):
        assert multiplicity_test(a, family.value, family.count) == "confirmed", family
    assert np.linalg.eigvals(a).real.max() < 0


def test_the_papers_first_four_families_agree_and_its_beta_family_is_not_an_eigenvalue():
    config = make_config(platoon={"count": 4})
    a, _ = jacobian(config)
    families = paper_eigenvalues(config, 4)
    for family in families[:4]:
        assert multiplicity_test(a, family.value, family.count) == "confirmed"
    for family in families[4:]:  # -(1-beta) k_v and -beta k_v with beta = 0.95
        assert multiplicity_test(a, family.value, 1) == "not an eigenvalue"


def test_regular_law_has_no_equilibrium_at_the_papers_x_eq():
    _, residual = jacobian(make_config(platoon={"count": 2, "law": "regular"}))
    assert residual > 1e-3


def test_a_clockwise_circle_has_the_mirrored_equilibrium():
    _, residual = jacobian(make_config(path={"direction": "cw"}, platoon={"count": 3}))
    assert residual < 1e-9


@pytest.mark.parametrize("count", [4, 6])
def test_the_speed_chain_printed_in_the_papers_text_destabilizes_the_platoon(count):
    """V_cmd,i = V_(i+1) d*/d_i (the paper's text) instead of d_(i+1) (its linearization, our FMUs)."""
    config = make_config(platoon={"count": count})
    follower, _ = jacobian(config)
    own, _ = jacobian(config, speed_chain_gap="own")
    assert np.linalg.eigvals(follower).real.max() < -0.2
    assert np.linalg.eigvals(own).real.max() > 0.01


@pytest.mark.parametrize("k_v", [0.5, 2.0, 8.0])
def test_speed_chain_peak_gain_is_the_peak_of_the_link_transfer_function_and_above_one(k_v):
    """The closed-form peak equals a dense frequency sweep of G(s) = (k_v s + k)/(s^2 + k_v s + k)."""
    config = make_config(path={"radius": 2000.0}, platoon={"k_v": k_v})
    p = config.platoon
    k = k_v * p.speed * math.sqrt(1.0 - (p.d_star / (2.0 * config.path.radius)) ** 2) / p.d_star
    w = np.linspace(1e-4, 5.0, 200001)
    sweep = np.abs((k_v * 1j * w + k) / (-(w**2) + k_v * 1j * w + k))
    peak = peak_gain(chain_of(config, ideal=True))
    gain, frequency = peak.gain, peak.frequency
    assert gain == pytest.approx(sweep.max(), rel=1e-9)
    assert frequency == pytest.approx(w[sweep.argmax()], abs=1e-3)
    assert gain > 1.0  # never string stable, only less so as k_v grows


def test_a_hundred_vehicle_speed_chain_amplifies_by_trillions_at_the_papers_k_v():
    """docs/model.md, section 10: 1.3416 per link at R = 2000 m, 4.3e12 over 99 links; k_v = 2: 3.1e4."""
    peak = peak_gain(chain_of(make_config(path={"radius": 2000.0}), ideal=True))
    gain, frequency = peak.gain, peak.frequency
    assert gain == pytest.approx(1.3416, abs=1e-4) and frequency == pytest.approx(0.333, abs=1e-3)
    assert gain**99 > 1e12
    assert peak_gain(chain_of(make_config(path={"radius": 2000.0}, platoon={"k_v": 2.0}), ideal=True)).gain ** 99 < 1e5


@pytest.mark.parametrize("count", [30, 100])
def test_the_verdict_of_a_long_platoon_comes_from_the_families_not_from_rounding_scattered_eigenvalues(count):
    """At 100 vehicles the computed eigenvalues' largest real part is positive (rounding around a
    100-fold eigenvalue), yet the platoon is stable: the verdict must say stable, with the families'
    -V_c alpha/d*, and name the computed value as unreliable."""
    from orchestrator.analysis.linear import eigen_report

    config = make_config(platoon={"count": count})
    verdict = next(line for line in eigen_report(config).splitlines() if line.startswith("verdict:"))
    families = our_families(config, count)
    largest = max(f.value.real for f in families)
    assert verdict.startswith("verdict: exponentially stable")
    assert f"{largest:+.6f}, from the closed-form families" in verdict
    assert "scatter" in verdict


def test_a_short_platoon_keeps_the_computed_verdict():
    from orchestrator.analysis.linear import eigen_report

    config = make_config(platoon={"count": 4})
    a, _ = jacobian(config)
    verdict = next(line for line in eigen_report(config).splitlines() if line.startswith("verdict:"))
    assert verdict == f"verdict: exponentially stable (largest real part {np.linalg.eigvals(a).real.max():+.6f})"


def test_the_report_says_why_the_computed_eigenvalues_split_around_a_repeated_family():
    """Four vehicles: the 4-fold family -0.440959 +- 0.471405j comes out of the solver as four values up to a
    few 1e-3 away; the report says so, with that distance as computed, before the families it confirms."""
    from orchestrator.analysis.linear import eigen_report

    config = make_config(platoon={"count": 4})
    a, _ = jacobian(config)
    families = our_families(config, 4)
    spread = max(min(abs(value - family.value) for family in families) for value in np.linalg.eigvals(a))
    assert 1e-6 < spread < 1e-2  # split, yet near: what the note explains
    lines = eigen_report(config).splitlines()
    note = next(index for index, line in enumerate(lines) if line.startswith("  (a repeated root is computed"))
    assert f"these lie up to {spread:.1e} 1/s from the families below, which are tested by rank" in lines[note]
    assert lines[note + 1].startswith("eigenvalue families [1/s]")
