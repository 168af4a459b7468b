"""The linearization about the circular equilibrium, from the same model code the FMUs run."""

from __future__ import annotations

import numpy as np
import pytest

from orchestrator.analysis import jacobian, multiplicity_test, our_families, paper_eigenvalues
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
