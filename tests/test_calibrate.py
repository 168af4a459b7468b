"""`platoon calibrate`'s identification, without a network: the path it fits is the model's own, and it finds
a robot made by the model itself (tests/calibration_support.py) within the issue's floors; the robot truth
file the emulator reads. The real emulator and real runs: tests/test_calibrate_live.py (paced)."""

from __future__ import annotations

import math
import random

import numpy as np
import pytest

from bridge.emulator import EmulatedRobot, EmulatorSettings, RobotSpec
from bridge.protocol import RobotKeys, WheelCommand
from bridge.robot_truth import RobotTruth, TruthError, load_truth
from fmus.model.dynamics import M3piDynamics
from orchestrator.analysis.calibrate import calibrate_robot
from orchestrator.analysis.wheel_path import dead_reckon, rigid_fit, wheel_targets
from tests.calibration_support import BOUNDS, random_truth, synthetic_record

# the floors of issue 51: 3 % of the truth, latencies within 3 ms, the dead-band within 3 mm/s
ABSOLUTE = {"command_latency": 0.003, "pose_latency": 0.003, "wheel_deadband": 0.003}


def test_the_numpy_wheel_targets_are_the_models_wheel_target_bit_for_bit() -> None:
    rng = np.random.default_rng(3)
    commands = np.concatenate([rng.uniform(-1.5, 1.5, 2000), [0.0, -0.0, 0.03, -0.03, 0.0299999, 0.9, -0.9, 1.2]])
    for gain, limit, deadband in ((1.0, 1.0, 0.0), (1.13, 0.9, 0.03), (0.87, 0.6, 0.05)):
        model = M3piDynamics(0.5, wheel_speed_max=limit, wheel_deadband=deadband)
        twin = wheel_targets(model, commands, gain)
        expected = np.array([model.wheel_target(c, gain) for c in commands.tolist()])
        assert twin.tobytes() == expected.tobytes()


def test_the_fitted_path_is_the_integrated_drive_to_micrometres() -> None:
    """The exact-lag path against RK4 on M3piDynamics.drive (1 ms substeps, as the emulator), deadline lapses and
    a dead-band included: what remains is RK4's error and Simpson's, far below the poses' 2 mm."""
    truth = {"wheel_gain_right": 1.1, "wheel_gain_left": 0.9, "motor_time_constant": 0.07, "wheel_speed_max": 0.8,
             "wheel_deadband": 0.03, "command_latency": 0.02}
    record = synthetic_record(truth, seconds=15.0, noise=False)
    model = M3piDynamics(0.5, **{k: v for k, v in truth.items() if k != "command_latency"})
    path = dead_reckon(model, record.commands, truth["command_latency"], record.stamp)
    x, y, _ = rigid_fit(path.x, path.y, record.x, record.y, np.zeros(len(record.x), dtype=int))
    assert float(np.max(np.hypot(x - record.x, y - record.y))) < 1e-5


def identification_misses(calibration, truth: dict[str, float], hop: float = 0.0) -> list[str]:
    """Every parameter off the floors: an identified one more than 3 % (3 ms, 3 mm/s) from the truth, and any
    other not identified. The command latency found is the loop's whole delay, the truth's command and pose
    latencies together (a pose older than its stamp shows in the path as a later command: docs/hil.md) plus
    ``hop``, the commands' way from the run to the robot side (a live run's: milliseconds on a loaded machine), and
    the pose latency is never identified on its own (written as the nominal 0). The one other exception: a
    dead-band too small to tell from none, which must then be written as the nominal 0 with the truth inside
    its interval."""
    misses = []
    loop = {**truth, "command_latency": hop + truth.get("command_latency", 0.0) + truth.get("pose_latency", 0.0)}
    for name, estimate in calibration.estimates.items():
        expected = loop.get(name, 0.084 if name == "track" else None)
        if name == "pose_latency":
            if estimate.identified or estimate.value != 0.0:
                misses.append(f"pose_latency {estimate.value} identified apart from the command latency")
            continue
        if not estimate.identified:
            small = name == "wheel_deadband" and estimate.value == 0.0 and estimate.low <= expected <= estimate.high
            if not small:
                misses.append(f"{name} not identified: {estimate.note}")
            continue
        tolerance = ABSOLUTE.get(name, 0.03 * abs(expected))
        if abs(estimate.value - expected) > tolerance:
            misses.append(f"{name} {estimate.value:.5g} (truth {expected:.5g})")
    return misses


@pytest.mark.parametrize("seed", [11, 12])
def test_calibrate_finds_a_random_model_made_robot_within_the_floors(seed: int) -> None:
    truth = random_truth(random.Random(seed))
    calibration = calibrate_robot([synthetic_record(truth, seed=seed)])
    assert not identification_misses(calibration, truth)
    # the calibrated path is as close to the poses as their own noise allows; the nominal model is centimetres off
    assert calibration.residual < 1.05 * calibration.pose_noise
    assert calibration.residual_before > 5 * calibration.pose_noise
    for name, estimate in calibration.estimates.items():
        if name in BOUNDS:
            assert estimate.low <= estimate.value <= estimate.high


def test_what_the_trace_did_not_excite_is_not_identified_and_stays_nominal() -> None:
    """No stretch at the limit and no command near zero: the limit and the dead-band are "not identified" and
    written as the model's nominal values, never as the fit's guess; the rest is still found."""
    truth = {**random_truth(random.Random(5)), "wheel_speed_max": 0.95}
    calibration = calibrate_robot([synthetic_record(truth, seconds=30.0, full=False)])
    limit, deadband = calibration.estimates["wheel_speed_max"], calibration.estimates["wheel_deadband"]
    assert not limit.identified and "never reached" in limit.note and limit.value == 1.0
    assert not deadband.identified and deadband.value == 0.0
    gain = calibration.estimates["wheel_gain_right"]
    assert gain.identified and abs(gain.value - truth["wheel_gain_right"]) < 0.03 * truth["wheel_gain_right"]


def test_a_truth_file_gives_each_robot_its_own_physics_over_a_default(tmp_path) -> None:
    path = tmp_path / "truth.toml"
    path.write_text("[default]\nposition_noise = 0.002\ncommand_latency = 0.01\n"
                    "[robots.3]\nwheel_gain_right = 1.1\ncommand_latency = 0.03\n")
    truths = load_truth(path)
    three, four = truths.robot(3), truths.robot(4)
    assert (three.wheel_gain_right, three.command_latency, three.position_noise) == (1.1, 0.03, 0.002)
    assert (four.wheel_gain_right, four.command_latency) == (None, 0.01)
    model = M3piDynamics(0.5, track=0.09)
    assert three.dynamics(model) == M3piDynamics(0.5, track=0.09, wheel_gain_right=1.1)
    assert four.dynamics(model) == model


@pytest.mark.parametrize("text, expected", [
    ("[robots.3]\nwheel_gain = 1.1\n", "[robots.3]: unknown key 'wheel_gain'"),
    ("[robots.3]\nmotor_time_constant = 0\n", "[robots.3].motor_time_constant = 0: expected a number > 0"),
    ("[default]\ncommand_latency = -0.01\n", "[default].command_latency = -0.01: expected a number >= 0"),
    ("[robots.three]\ntrack = 0.08\n", "[robots.three]: expected a robot id"),
    ("[robot.3]\ntrack = 0.08\n", "unknown table 'robot'"),
    ("[default]\ntrack = \"wide\"\n", "[default].track = 'wide': expected a finite number"),
    ("[default\n", "not TOML"),
])
def test_a_bad_truth_file_is_one_line_naming_the_table_and_key(tmp_path, text: str, expected: str) -> None:
    path = tmp_path / "truth.toml"
    path.write_text(text)
    with pytest.raises(TruthError) as error:
        load_truth(path)
    assert expected in str(error.value) and str(path) in str(error.value) and "\n" not in str(error.value)


def test_each_emulated_robot_has_its_own_latency_and_noise_over_the_settings() -> None:
    settings = EmulatorSettings(command_latency=0.05, position_noise=0.0)
    model = M3piDynamics(0.5)
    own = RobotSpec(RobotKeys("platoon", 3), 0.0, 0.0, 0.0, 0.3, model, RobotTruth(command_latency=0.01,
                                                                                      position_noise=0.004))
    plain = RobotSpec(RobotKeys("platoon", 4), 0.0, 0.0, 0.0, 0.3, model)
    robots = [EmulatedRobot(spec, settings, lambda text: None) for spec in (own, plain)]
    assert [(r.command_latency, r.position_noise, r.pose_latency) for r in robots] == [(0.01, 0.004, 0.0),
                                                                                      (0.05, 0.0, 0.0)]
    for robot in robots:
        robot.time = 100.0
        robot.queue(WheelCommand(1, 101.0, 0.3, 0.3, 0), 100.0)
        robot.advance(100.02)
    assert robots[0].command_seq == 1 and robots[1].command_seq == 0  # 10 ms of radio applied, 50 ms not yet
    noise = random.Random(1)
    spread = np.std([robots[0].sample(100.02 + 1e-9 * k, noise).x for k in range(400)])
    assert 0.003 < spread < 0.005 and robots[1].sample(100.03, noise).x == robots[1].state[0]
    assert math.isfinite(spread)


def test_compare_prints_each_vehicles_path_and_speed_differences(tmp_path) -> None:
    """Two all-FMU runs of the experiment, one 2 cm/s faster: compare names the vehicle with the rms and the
    largest distance between the two paths (as the traces read back give them), and a run against itself is 0."""
    import subprocess

    from orchestrator.analysis.compare import run_differences
    from orchestrator.trace import load
    from tests.test_hil import PLATOON, REPO, _env

    traces = []
    for name, sets in (("nominal", []), ("faster", ["--set", "platoon.speed=0.32"])):
        trace = tmp_path / f"{name}.mcap"
        run = subprocess.run([str(PLATOON), "run", "configs/hil/calibrate.toml", "-q", "--out", str(trace), "--set",
                              "vehicles.1.endpoint=fmu", "--set", "simulation.stop_time=8.0", *sets], cwd=REPO,
                             env=_env(), capture_output=True, text=True, timeout=120)
        assert run.returncode == 0, run.stderr
        traces.append(trace)
    a, b = load(traces[0]).component("vehicle1"), load(traces[1]).component("vehicle1")
    distance = np.hypot(a["x"] - b["x"], a["y"] - b["y"])
    [difference] = run_differences(load(traces[0]), load(traces[1]))
    assert difference.path_rms == pytest.approx(float(np.sqrt(np.mean(distance ** 2))), rel=1e-12)
    assert difference.path_max == float(distance.max()) > 0.05 and difference.speed_max > 0.01
    assert run_differences(load(traces[0]), load(traces[0]))[0].path_max == 0.0
    shown = subprocess.run([str(PLATOON), "compare", *map(str, traces)], cwd=REPO, env=_env(), capture_output=True,
                           text=True, timeout=120)
    assert shown.returncode == 0, shown.stderr
    assert "vehicle1" in shown.stdout and f"{difference.path_rms * 1e3:.2f} mm" in shown.stdout
