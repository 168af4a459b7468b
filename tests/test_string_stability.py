"""String stability, analytic and measured, held together (docs/model.md, section 12).

* the channel model of the analysis (age of the message in use, with beacons, losses and bursts) is
  the age distribution the Link model (fmus/model/link.py) produces;
* the closed forms: acc is string stable iff k_v h >= 2 alpha; cacc with a pure delay theta on the
  communicated speed (held) needs h >= sqrt(2 theta / k_p); the paper's chain peaks at 1.3416;
* on a grid of laws x k_v or time gap x link delay, a co-simulation (native FMUs, links as Link FMUs)
  pushed by a sinusoid at the analytic peak frequency measures the l2 gain the analysis predicts;
* `platoon stability` reads a trace back and prints those gains next to the closed form.
"""

from __future__ import annotations

import math
import numpy as np
import pytest

from fmus.model.link import LinkParameters, LinkStepper
from orchestrator.analysis.error_gains import link_gains, propagation, vehicle_errors
from orchestrator.analysis.chain_model import chain_model
from orchestrator.analysis.sampled_chain import cascade_speeds, growth_per_link
from orchestrator.analysis.string_stability import (Chain, Channel, chain_of, interior_vehicle, peak_gain,
                                                    smallest_time_gap)
from orchestrator.execution.run import run_scenario
from orchestrator.scenario.config import config_from_mapping
from orchestrator.trace import load


# --- the channel model against the Link model ----------------------------------------------------------------

@pytest.mark.parametrize("loss, burst, period, delay", [(0.0, 1.0, 0.0, 0.3), (0.3, 1.0, 0.0, 0.0), (0.5, 4.0, 0.1, 0.2),
                                                        (0.2, 1.0, 0.25, 0.05)])
def test_the_channels_age_transform_is_the_link_models_age_distribution(loss, burst, period, delay):
    """E[e^{-jwA}] over the ages a Jacobi receiver works with (the link's age at each step, growing over the
    step), from 200 000 steps of the Link model, against Channel.age_transform. The Monte-Carlo error of a
    mean of unit phasors over N samples correlated over ~K steps is ~sqrt(K/N): 0.01 for K = 20 here."""
    step, steps = 0.01, 200_000
    link = LinkStepper(LinkParameters(delay=delay, period=period, loss=loss, burst=burst, seed=7), 0.0)
    ages = np.empty(steps)
    link.in_time = 0.0
    for k in range(steps):
        link.in_time = k * step  # the sender's message of this communication point (Jacobi: outputs at t)
        link.step(k * step, step)
        ages[k] = link.outputs()["age"]  # at t + h: what the receiver uses over [t + h, t + 2h)
    ages = ages[1000:]
    w = np.array([0.3, 1.0, 3.0])
    within = np.where(w == 0, 1.0, (1 - np.exp(-1j * w * step)) / (1j * w * step))  # the age grows over the step
    measured = np.exp(-1j * np.outer(w, ages)).mean(axis=1) * within
    channel = Channel(max(step, math.ceil(delay / step - 1e-9) * step), max(period, step), 0, loss, burst)
    assert np.abs(measured - channel.age_transform(1j * w)).max() < 0.02


# --- closed forms -------------------------------------------------------------------------------------------

def test_acc_is_string_stable_exactly_from_a_time_gap_of_two_alpha_over_k_v():
    for k_v, alpha in [(0.5, 1.0), (2.0, 0.66)]:
        h = smallest_time_gap(Chain("acc", k_v, alpha))
        assert h == pytest.approx(2.0 * alpha / k_v, rel=1e-4)


@pytest.mark.parametrize("delay", [0.1, 0.3, 1.0])
def test_cacc_with_a_held_delayed_speed_needs_a_time_gap_of_sqrt_two_delay_over_k_p(delay):
    """|G|^2 = 1 + c w^2 + ... with c ~ 2 k_p theta - k_p^2 h^2: the low-frequency condition, which binds."""
    chain = Chain("cacc", 1.0, time_gap=1.0, cacc_gain=0.2, backward=Channel(delay, 0.0, 0))
    assert smallest_time_gap(chain) == pytest.approx(math.sqrt(2.0 * delay / 0.2), rel=1e-3)


def test_a_delay_is_harmless_to_cacc_when_extrapolated_and_costly_when_held():
    """The receiver knows each message's age: extrapolating the speed along its rate cancels a delay to
    first order (e^{-s theta}(1 + s theta) = 1 - (s theta)^2/2 + ...), holding it does not."""
    held = Chain("cacc", 1.0, time_gap=1.0, cacc_gain=0.2, backward=Channel(0.5, 0.0, 0))
    extrapolated = Chain("cacc", 1.0, time_gap=1.0, cacc_gain=0.2, backward=Channel(0.5, 0.0, 1))
    assert not peak_gain(held).string_stable and peak_gain(extrapolated).string_stable


def test_the_papers_chain_peaks_at_1_3416_and_a_forward_delay_raises_it():
    paper = Chain("paper", 0.5, math.sqrt(1.0 - (75.0 / 4000.0) ** 2), 25.0, 75.0)
    peak = peak_gain(paper)
    assert peak.gain == pytest.approx(1.3416, abs=1e-4) and peak.frequency == pytest.approx(0.333, abs=1e-3)
    delayed = peak_gain(Chain("paper", 0.5, paper.alpha, 25.0, 75.0, forward=Channel(1.0, 0.0, 0)))
    assert delayed.gain > peak.gain and delayed.unstable_roots == 0
    # a long enough delay inside the paper's loop destabilizes the platoon itself, not only the chain
    assert peak_gain(Chain("paper", 0.5, paper.alpha, 25.0, 75.0, forward=Channel(8.0, 0.0, 0))).unstable_roots > 0


# --- analytic and measured on a grid ------------------------------------------------------------------------

STEP = 0.01
START, SETTLE, PERIODS = 10.0, 60.0, 40.0  # s: the sinusoid starts, its transient dies out, then >= 40 s measured
AMPLITUDE = 0.01  # m/s against V_c = 25: second-order terms ~4e-4 of the response
PROBE = 0.3  # rad/s: where a string-stable chain (peak at w -> 0) is probed
COUPLING = "extrapolate"  # the default; see TOLERANCE
# Where the analysis applies: small disturbances (linear), the chain's own transient gone (slowest pole
# here -0.2 1/s: e^{-0.2 * 60} = 6e-6), and the fundamental-harmonic model of the sampling (a 0.01 s step):
# it leaves out the ripple a sampled, extrapolated message carries at 2 pi/T +- w, which the next
# sampling folds back onto w. That grows like w^2 A T (A the message's age): the grid's worst case, cacc
# with h = 0.5 s and a 0.5 s delay peaking at 3.6 rad/s, measures 1.0321 against 1.0246 (0.7 %); with
# a 0.05 s step it measured 1.094 against 1.056 (3.6 %), which is why the step is 0.01 s. The other
# cases agree to 0.3 %. 1 % holds these and still separates a 1.02 gain from a 1.
TOLERANCE = 0.01
GRID = [(law, key, value, delay)
        for law, key, values in [("paper", "k_v", (0.5, 2.0)), ("acc", "time_gap", (3.0, 5.0)), ("cacc", "time_gap", (0.5, 2.0))]
        for value in values for delay in (0.0, 0.5)]


def _grid_config(law: str, key: str, value: float, delay: float, frequency: float | None, periods: float):
    """Five vehicles on a line, started at the law's equilibrium: d* = 75 m, or h V_c when a time gap needs
    more (the default standstill gap d* - h V_c then 0), links with ``delay`` both ways."""
    count = 5
    platoon = {"count": count, "speed_law": law, "d_star": max(75.0, 25.0 * value if key == "time_gap" else 0.0),
               "speed": 25.0, key: value}
    raw = {"name": "grid", "path": {"kind": "line"}, "platoon": platoon,
           "simulation": {"step": STEP, "max_substep": STEP, "stop_time": START + SETTLE + periods, "fmus": "native",
                          "coupling": COUPLING}}
    if delay:
        raw["links"] = {"delay": delay}
    if frequency is not None:
        raw["disturbance"] = [{"vehicle": count if law == "paper" else 1, "kind": "speed", "start": START,
                               "duration": SETTLE + periods, "value": AMPLITUDE, "frequency": frequency}]
    return config_from_mapping(raw)


@pytest.mark.parametrize("law, key, value, delay", GRID)
def test_the_measured_l2_gain_is_the_analytic_gain_at_the_peak_frequency(law, key, value, delay, native_fmu_dir, tmp_path):
    """A sinusoid at the ideal chain's peak frequency (or at PROBE when it is string stable) on the vehicle the
    law propagates from; the l2 gain of the speed errors over the steady part, from the second vehicle past
    the pushed one to the next, against the sampled-data cascade's gain for those links (links as the run
    wires them); the last link grows where the cascade's growth per link is above 1, and only there."""
    ideal = peak_gain(chain_of(_grid_config(law, key, value, delay, None, PERIODS), ideal=True))
    frequency = ideal.frequency if not ideal.string_stable else PROBE
    period = 2.0 * math.pi / frequency
    periods = math.ceil(PERIODS / period) * period
    config = _grid_config(law, key, value, delay, frequency, periods)
    result = run_scenario(config, "", tmp_path / "grid.mcap", foxglove=False)
    assert result.status == "completed", result.error
    trace = load(result.trace)
    window = (START + SETTLE, START + SETTLE + periods)
    source = config.disturbance[0].vehicle
    order = propagation(config, trace.vehicles(), source)
    # from the second vehicle past the pushed one: the pushed vehicle's disturbance is held over each step,
    # a staircase whose jumps its speed_rate output does not carry (the cascade models it; the l2 gain
    # of those first links also holds the ripple it makes, which the fit at w leaves out)
    gains = [g.l2["speed"] for g in link_gains(vehicle_errors(trace, config), order, window)[2:]]
    numbers = [trace.vehicles().index(name) + 1 for name in order]
    amplitudes = np.abs(cascade_speeds(chain_model(config), numbers, frequency, 1))
    expected = (amplitudes[1:] / amplitudes[:-1])[2:]
    assert np.abs(np.array(gains) / expected - 1.0).max() < TOLERANCE, (gains, expected)
    # far enough down the string every link grows by the cascade's spectral radius: the last link measured
    # is on its side of 1 (an earlier one need not be: cacc h = 0.5 s with a 0.5 s delay measures 1.0017,
    # then 0.9975 against a growth of 0.9975 at 0.3 rad/s)
    growth = growth_per_link(chain_model(config), interior_vehicle(config), np.array([frequency]))[0]
    assert (gains[-1] > 1.0) == (growth > 1.0), (gains, growth)


# --- platoon stability ---------------------------------------------------------------------------------------

def _platoon(*args, cwd):
    import subprocess
    import sys

    return subprocess.run([sys.executable, "-m", "orchestrator", *map(str, args)], cwd=cwd, capture_output=True,
                          text=True, timeout=600)


def test_platoon_stability_prints_the_gains_and_the_closed_form_beside_them(native_fmu_dir, tmp_path):
    """The study's platoon under cacc with a 0.3 s link, its head (the target) pushed: each probe frequency's
    measured gain per clean link beside the sampled-data cascade's prediction for this run (4 digits apart:
    tests/test_sampled_chain.py), and a headline verdict from those links only, which is the closed form's."""
    from pathlib import Path

    study = Path(__file__).resolve().parent.parent / "configs" / "study" / "string_stability.toml"
    trace = tmp_path / "cacc.mcap"
    ran = _platoon("run", study, "--set", "platoon.speed_law=cacc", "--set", "links.delay=0.3", "-q", "--out", trace,
                   cwd=tmp_path)
    assert ran.returncode == 0, ran.stderr
    shown = _platoon("stability", trace, cwd=tmp_path)
    assert shown.returncode == 0, shown.stderr
    # the table shows every link: from the pushed target (the head of the chain), to the pushed vehicle 7
    assert "target -> vehicle1" in shown.stdout and "vehicle6 -> vehicle7" in shown.stdout
    assert ("over the links that measure propagation (vehicle3 -> vehicle4 -> vehicle5 -> vehicle6)" in shown.stdout
            and "does not grow along the platoon" in shown.stdout), shown.stdout
    assert ("closed form (sampled-data cascade): growth per link far down the string peaks at 1.0000 as w -> 0; no link "
            "inside the vehicle's own loop: string stable") in shown.stdout
    rows = [line.split(":", 1)[1] for line in shown.stdout.splitlines() if line.strip().startswith(("0.1 rad/s", "3 rad/s"))]
    assert len(rows) == 2, shown.stdout
    for row in rows:  # " predicted 0.9960, 0.9986; measured 0.9960, 0.9986"
        predicted, measured = (np.array([float(v) for v in part.split(None, 1)[1].split(",")])
                               for part in row.split(";"))
        assert np.abs(measured / predicted - 1.0).max() < 1e-3, shown.stdout


def test_platoon_stability_refuses_a_run_without_disturbance_in_one_line(native_fmu_dir, tmp_path):
    from pathlib import Path

    paper = Path(__file__).resolve().parent.parent / "configs" / "paper" / "platoon.toml"
    trace = tmp_path / "calm.mcap"
    assert _platoon("run", paper, "--set", "simulation.stop_time=2", "-q", "--out", trace, cwd=tmp_path).returncode == 0
    shown = _platoon("stability", trace, cwd=tmp_path)
    assert shown.returncode == 2 and shown.stderr.strip().count("\n") == 0
    assert "has no [[disturbance]]" in shown.stderr and "Traceback" not in shown.stderr


def test_analyze_s_verdict_is_the_l2_gain_s_even_where_the_peaks_shrink() -> None:
    """configs/paper/platoon_back_speed.toml as `platoon analyze` measured it (2026-12-02): the speed peaks
    shrink toward the front (l_inf 0.44, 0.65, 0.99) while the l2 gain from vehicle 2 to vehicle 1 is 1.11.
    The verdict follows the l2 gain and says so, naming the peaks as the other column (docs/reproduction.md
    reads that row the same way)."""
    from orchestrator.analysis.error_gains import LinkGains, gains_lines

    nan = float("nan")
    measured = [("vehicle4", "vehicle3", 0.5783, 0.4437), ("vehicle3", "vehicle2", 0.9932, 0.6491),
                ("vehicle2", "vehicle1", 1.1132, 0.9878)]
    gains = [LinkGains(a, b, {"speed": l2, "gap": nan}, {"speed": linf, "gap": nan}) for a, b, l2, linf in measured]
    verdict = gains_lines(gains)[-1]
    assert verdict.startswith("  largest speed l2 gain past the disturbed vehicle: 1.1132: this disturbance grows "
                              "along the platoon (the l2 gain decides"), verdict
    assert "the l_inf column, the peaks, may shrink while it grows" in verdict
    shrinking = [LinkGains(g.sender, g.receiver, {"speed": 0.9 * g.l2["speed"] / 1.1132, "gap": nan}, g.linf) for g in gains]
    assert "this disturbance does not grow along the platoon" in gains_lines(shrinking)[-1]
