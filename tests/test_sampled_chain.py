"""The sampled-data cascade (orchestrator/analysis/sampled_chain.py) against the co-simulation it models.

* its loss weights are the age law the phase-averaged channel uses (one law of the beacons in use);
* on the study's platoon (configs/study/string_stability.toml: seven vehicles on a line, 10 Hz beacons,
  four sinusoids on both ends, the virtual target and vehicle 7), the component at each probe frequency of
  every vehicle's speed (and the target's), as a least-squares fit over the run measures it, is the
  cascade's, link by link: the paper's law with held coupling (where the backward link sits inside the
  speed loop), cacc with extrapolated 0.3 s links, acc;
* the cacc delay boundary `platoon analyze` gives is where runs of the co-simulation start to grow.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from orchestrator.analysis.error_gains import (clean_order, component_index, frequency_gains, probe_frequencies,
                                               propagation, source_vehicle, steady_window, stretch_growth,
                                               vehicle_errors)
from orchestrator.analysis.chain_model import chain_model, loss_weights
from orchestrator.analysis.sampled_chain import cascade_speeds, largest_stable_delay
from orchestrator.analysis.string_stability import Channel, _hold, interior_vehicle
from orchestrator.execution.run import run_scenario
from orchestrator.scenario.config import load_config
from orchestrator.trace import load

STUDY = Path(__file__).resolve().parent.parent / "configs" / "study" / "string_stability.toml"


@pytest.mark.parametrize("loss, burst", [(0.4, 1.0), (0.8, 1.0), (0.5, 4.0)])
def test_the_loss_weights_are_the_channels_law_of_the_beacon_in_use(loss, burst):
    """sum_j w_j z^j is the factor L(z) of Channel.age_transform (the renewal law of the beacons since the
    last delivery): the two models agree on which beacon is in use, they differ in what they do with it."""
    weights = loss_weights(loss, burst)
    assert sum(weights) == pytest.approx(1.0, abs=1e-13)
    s = 1j * np.array([0.3, 3.0, 20.0])
    z = np.exp(-0.1 * s)
    ours = sum(w * z**j for j, w in enumerate(weights))
    channel = Channel(0.0, 0.1, 0, loss, burst)
    assert np.abs(ours - channel.age_transform(s) / _hold(s, 0.1)).max() < 1e-12


def _measured_and_predicted(overrides: list[str], tmp_path: Path):
    """Per probe frequency, every link's gain along the way the law carries a disturbance: measured on a run
    of the study, and the cascade's."""
    config, _ = load_config(STUDY, overrides)
    result = run_scenario(config, "", tmp_path / "run.mcap", foxglove=False)
    assert result.status == "completed", result.error
    trace = load(result.trace)
    names = trace.vehicles()
    order = propagation(config, names, source_vehicle(config))
    frequencies = probe_frequencies(config)
    window = steady_window(config, float(trace.component(names[0])["t"][-1]))
    measured = np.array(frequency_gains(vehicle_errors(trace, config), order, frequencies, window))
    numbers = [component_index(name, names) for name in order]
    predicted = []
    for w in frequencies:
        amplitudes = np.abs(cascade_speeds(chain_model(config), numbers, w, config.simulation.trace_every))
        predicted.append(amplitudes[1:] / amplitudes[:-1])
    return config, trace, measured, np.array(predicted)


# The study's laws are linear on a line but for the paper's V d*/d, whose second-order terms mix the larger
# probes into the 3 rad/s component, which has fallen to 0.31^6 of vehicle 7's 5 mm/s push at vehicle 1
# (measured: 0.12 % on that link with 0.3 s held links, 4 digits on every other link and law). 5e-3 holds
# that and is far below the 7 % the phase-averaged model is off by at 3 rad/s.
TOLERANCE = 5e-3


@pytest.mark.parametrize("overrides", [
    ["platoon.speed_law=paper", "links.delay=0.3", "simulation.coupling=hold"],
    ["platoon.speed_law=cacc", "links.delay=0.3"],
    ["platoon.speed_law=acc", "links.delay=0.2", "links.loss=0.6"],
], ids=["paper-hold", "cacc-extrapolate", "acc"])
def test_the_cascade_is_what_every_link_of_a_run_measures(overrides, native_fmu_dir, tmp_path):
    _, _, measured, predicted = _measured_and_predicted(overrides, tmp_path)
    assert np.abs(measured / predicted - 1.0).max() < TOLERANCE, (measured, predicted)


def test_the_papers_law_with_held_links_has_the_backward_link_in_its_loop(native_fmu_dir, tmp_path):
    """0.3 s links, held: the gap a follower sends is its distance to the vehicle ahead as its backward link
    shows it, so both links delay vehicle i's own position in its loop; the measured gain per link at
    0.3 rad/s is 1.3769 (the forward link alone gave 1.2506)."""
    config, _, measured, predicted = _measured_and_predicted(
        ["platoon.speed_law=paper", "links.delay=0.3", "simulation.coupling=hold"], tmp_path)
    k = probe_frequencies(config).index(0.3)
    assert predicted[k][2:5] == pytest.approx(1.3769, abs=1e-4)
    assert measured[k][2:5] == pytest.approx(1.3769, abs=1e-3)


def _clean_growth(config, trace) -> float:
    """The headline's number: the largest growth per link at the probes over the clean links."""
    names = trace.vehicles()
    clean = clean_order(config, names)
    window = steady_window(config, float(trace.component(names[0])["t"][-1]))
    return stretch_growth(frequency_gains(vehicle_errors(trace, config), clean, probe_frequencies(config), window))


def test_the_cacc_delay_boundary_is_where_runs_start_to_grow(native_fmu_dir, tmp_path):
    """The study under cacc, no loss: `platoon analyze`'s cascade is string stable for link delays up to
    0.38 s; the co-simulation at 0.38 s does not grow on the links that measure propagation, at 0.39 s
    (0.40 s on the step grid) it does (at the 3 rad/s probe, near the cascade's peak at 2.8 rad/s)."""
    config, _ = load_config(STUDY, ["platoon.speed_law=cacc"])
    def with_delay(delay: float):
        return chain_model(config.model_copy(update={"links": config.links.model_copy(update={"delay": delay})}))

    assert largest_stable_delay(with_delay, interior_vehicle(config), config.simulation.step, longest=0.6) == pytest.approx(0.38)
    for delay, grows in ((0.38, False), (0.39, True)):
        run, _ = load_config(STUDY, ["platoon.speed_law=cacc", f"links.delay={delay}"])
        result = run_scenario(run, "", tmp_path / f"{delay}.mcap", foxglove=False)
        assert result.status == "completed", result.error
        assert (_clean_growth(run, load(result.trace)) > 1.0) == grows


def test_the_maps_scale_spends_its_range_above_1_and_its_axis_gives_the_age_of_information():
    """docs/string_stability.png: no peak is below 1 (every chain passes w -> 0 unchanged), so the colour
    scale gives 1 to the highest peak nearly all its colours; a tick names the delay and the ages it gives
    the receiver (a Link is one more hop under Jacobi: 0.02 s at delay 0, plus a 0.1 s beacon period)."""
    from orchestrator.sweep.stability_map import age_label, colour_scale

    norm, cmap = colour_scale(1.5)
    below = [cmap(norm(g)) for g in np.linspace(0.98, 0.999, 5)]
    above = [cmap(norm(g)) for g in np.linspace(1.001, 1.5, 50)]
    assert norm(1.0) < 0.05  # under 5 % of the scale below 1
    assert all(c[2] > c[0] for c in below) and all(c[0] >= c[2] for c in above)  # blue below 1, red above
    config, _ = load_config(STUDY, [])
    assert age_label(config, 0.0) == "0\n0.02-0.12" and age_label(config, 0.3) == "0.3\n0.3-0.4"


def test_the_headlines_growth_per_link_is_the_stretchs_amplitude_ratio_per_link():
    """At each probe the geometric mean of the clean links' gains, the last vehicle's amplitude over the
    first's to the power 1/links: one link's noise does not decide the verdict. The largest over the probes."""
    amplitudes = np.array([[1.0, 0.999, 0.9992, 0.997], [0.01, 0.0102, 0.0101, 0.0103]])  # probes x vehicles
    gains = amplitudes[:, 1:] / amplitudes[:, :-1]
    expected = (amplitudes[:, -1] / amplitudes[:, 0]) ** (1.0 / 3.0)
    assert stretch_growth(gains) == pytest.approx(expected.max(), rel=1e-14)
    assert gains[0].max() > 1.0 > stretch_growth(gains[:1])  # a single link above 1, the stretch below
