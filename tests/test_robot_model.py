"""A robot that is not its nominal model (docs/model.md): per-wheel gains, a dead-band, and the live run's
sampled loop with the radio's and the motion capture's latencies; their config keys and checks.

The C twin of the same model is held to it bit for bit in tests/test_native_fmus.py and tests/test_fmi3.py.
"""

from __future__ import annotations

import math

import pytest

from fmus.model.dynamics import M3piDynamics
from fmus.model.factory import controller_stepper, vehicle_parameter_errors, vehicle_stepper
from fmus.model.robot_loop import RobotLoopStepper
from fmus.model.vehicle import VehicleStepper
from orchestrator.scenario.config import ConfigError, config_from_mapping
from orchestrator.scenario.scenario import build_scenario, monolithic_refusal


def _values(**m3pi: float) -> dict:
    """Vehicle parameters of a lone m3pi chasing a target that circles a 1 m circle at 0.3 m/s (inputs held)."""
    values = {"law": "sine", "speed_law": "paper", "dynamics": "m3pi", "coupling": "extrapolate", "d_star": 0.6,
              "k_v": 2.0, "v_c": 0.3, "is_last": True, "max_substep": 0.001, "initial.x": 1.0, "initial.y": -0.2,
              "initial.heading": 1.4, "initial.speed": 0.25, "time_gap": 2.0, "standstill_gap": 0.0,
              "cacc_gain": 0.2, "m3pi.track": 0.084, "m3pi.wheel_speed_max": 1.0, "m3pi.motor_time_constant": 0.05,
              "m3pi.wheel_gain_right": 1.0, "m3pi.wheel_gain_left": 1.0, "m3pi.wheel_deadband": 0.0,
              "m3pi.command_latency": 0.0, "m3pi.pose_latency": 0.0, "speed_max": 0.0}
    values.update({f"m3pi.{key}": value for key, value in m3pi.items()})
    return values


def _drive(stepper: VehicleStepper, stop: float, step: float) -> list[tuple[float, float, float]]:
    """Step ``stepper`` behind a target on the unit circle (0.3 m/s, ccw, given exactly at each step): its poses."""
    poses = []
    for k in range(round(stop / step)):
        t = k * step
        angle = 0.3 * t
        stepper.target_x, stepper.target_y = math.cos(angle), math.sin(angle)
        stepper.target_heading, stepper.target_speed, stepper.target_time = angle + math.pi / 2, 0.3, t
        stepper.target_turn_rate = 0.3
        stepper.step(t, step)
        out = stepper.outputs()
        poses.append((out["x"], out["y"], out["heading"]))
    return poses


def _distance(a: list[tuple[float, float, float]], b: list[tuple[float, float, float]]) -> float:
    return max(math.hypot(p[0] - q[0], p[1] - q[1]) for p, q in zip(a, b))


# --- gains and dead-band -----------------------------------------------------------------------------------------

def test_a_wheel_follows_its_gain_and_ignores_commands_inside_its_dead_band():
    robot = M3piDynamics(k_v=1.0, wheel_gain_right=1.1, wheel_gain_left=0.9, wheel_deadband=0.03)
    # at rest, both wheels commanded 0.5 m/s: each heads for its own gain times the command
    d = robot.drive(0.0, 0.0, 0.0, 0.5, 0.5, 0.0)
    assert d[3] == pytest.approx(1.1 * 0.5 / 0.05) and d[4] == pytest.approx(0.9 * 0.5 / 0.05)
    # a command inside the dead-band: the wheel runs down to 0, whatever its gain; just outside, it heads for g c
    d = robot.drive(0.0, 0.2, 0.2, 0.029, -0.029, 0.0)
    assert d[3] == d[4] == pytest.approx(-0.2 / 0.05)
    assert robot.wheel_target(0.031, 1.1) == pytest.approx(1.1 * 0.031)
    # the gain cannot take a wheel beyond its limit
    assert robot.wheel_target(0.99, 1.1) == 1.0 and robot.wheel_target(-0.99, 1.1) == -1.0


def test_unequal_gains_turn_a_robot_commanded_straight():
    """Commanded straight ahead, a robot whose right wheel is stronger curves left: at steady state its wheels run at
    g_r c and g_l c and it turns at (g_r - g_l) c / W, the signature `platoon calibrate` fits."""
    robot = M3piDynamics(k_v=1.0, wheel_gain_right=1.05, wheel_gain_left=0.95)
    state = [0.0, 0.0, 0.0, 1.05 * 0.4, 0.95 * 0.4]
    d = robot.drive(state[2], state[3], state[4], 0.4, 0.4, 0.0)
    assert d[3] == pytest.approx(0.0, abs=1e-15) and d[4] == pytest.approx(0.0, abs=1e-15)
    assert d[2] == pytest.approx(0.1 * 0.4 / robot.track)


def test_a_calibrated_vehicle_drives_otherwise_than_the_nominal_one():
    nominal = _drive(vehicle_stepper(_values(), 0.0), 5.0, 0.01)
    calibrated = _drive(vehicle_stepper(_values(wheel_gain_right=1.1, wheel_gain_left=0.92, wheel_deadband=0.02),
                                        0.0), 5.0, 0.01)
    assert _distance(nominal, calibrated) > 0.005  # the guidance corrects, but not at once: millimetres to centimetres


# --- latencies: the sampled loop ---------------------------------------------------------------------------------

def test_latencies_of_zero_are_the_continuous_model_itself():
    """Both latencies 0 (every config before them): the very stepper of every run so far, hence the same numbers."""
    assert type(vehicle_stepper(_values(), 0.0)) is VehicleStepper
    assert type(vehicle_stepper({**_values(command_latency=0.02), "dynamics": "kinematic"}, 0.0)) is VehicleStepper
    assert isinstance(vehicle_stepper(_values(command_latency=0.02), 0.0), RobotLoopStepper)
    assert isinstance(vehicle_stepper(_values(pose_latency=0.005), 0.0), RobotLoopStepper)
    # the live run's controller is the continuous one whatever the latencies: they are the robot's own
    assert type(controller_stepper(_values(command_latency=0.02), 0.0)) is VehicleStepper


def test_a_sampled_loop_with_a_fast_radio_and_a_fast_loop_is_the_continuous_model():
    """Sampled every millisecond with a millisecond of latency, the loop drives as the continuous model: apart by
    what its late start makes (it stands until its first command lands, 1 ms at 0.25 m/s: 0.25 mm), no more. The
    loop is the model plus what sampling and delay add, nothing else."""
    continuous = _drive(vehicle_stepper(_values(), 0.0), 8.0, 0.001)
    sampled = _drive(vehicle_stepper(_values(command_latency=0.001), 0.0), 8.0, 0.001)
    assert 0.2e-3 < _distance(continuous, sampled) < 0.4e-3


def test_the_robot_stands_until_the_first_command_lands_then_each_acts_from_the_instant_it_lands():
    step, latency = 0.01, 0.025  # the delay is no multiple of the step: the command lands inside a step
    loop = vehicle_stepper(_values(command_latency=latency), 0.0)
    start = list(loop.robot)
    poses = _drive(loop, 0.02, step)  # two steps: the first command lands at 0.025 s
    assert poses[-1] == tuple(start[:3]) and loop.held == []
    assert len(loop.commands) == 6  # two commands in flight
    _drive_from(loop, 0.02, step)  # the third step: the first command lands 5 ms into it
    assert loop.held and loop.robot[:3] != start[:3]
    # 5 ms at the initial wheel speeds (their commands are near them), a straight-ish line of about 0.25 * 5 ms
    moved = math.hypot(loop.robot[0] - start[0], loop.robot[1] - start[1])
    assert moved == pytest.approx(0.25 * 0.005, rel=0.05)


def _drive_from(stepper: VehicleStepper, t: float, step: float) -> None:
    angle = 0.3 * t
    stepper.target_x, stepper.target_y = math.cos(angle), math.sin(angle)
    stepper.target_heading, stepper.target_speed, stepper.target_time = angle + math.pi / 2, 0.3, t
    stepper.step(t, step)


def test_the_two_latencies_add_up_in_the_motion():
    """The robot seen through the motion capture runs pose_latency behind itself, so a command moves it
    command_latency + pose_latency after it was sent: how the delay splits does not change the path."""
    radio = _drive(vehicle_stepper(_values(command_latency=0.03), 0.0), 6.0, 0.01)
    split = _drive(vehicle_stepper(_values(command_latency=0.02, pose_latency=0.01), 0.0), 6.0, 0.01)
    assert _distance(radio, split) < 1e-12  # only 0.02 + 0.01 != 0.03 in the last bit
    slower = _drive(vehicle_stepper(_values(command_latency=0.06), 0.0), 6.0, 0.01)
    assert _distance(radio, slower) > 1e-3


def test_a_late_robot_stays_stable_and_ends_behind_by_its_late_start():
    """40 ms of radio and 10 ms of motion capture (about the issue's worst robot) on a 10 ms loop: the loop stays
    stable and ends on the continuous model's path, behind it by what standing until the first command lands
    costs, V D = 0.3 m/s x 50 ms = 15 mm (a delay that destabilised the loop would leave it anywhere)."""
    continuous = _drive(vehicle_stepper(_values(), 0.0), 20.0, 0.01)
    late = _drive(vehicle_stepper(_values(command_latency=0.04, pose_latency=0.01), 0.0), 20.0, 0.01)
    (x, y, heading), (xc, yc, heading_c) = late[-1], continuous[-1]
    assert math.hypot(x - xc, y - yc) == pytest.approx(0.3 * 0.05, rel=0.15)
    assert heading == pytest.approx(heading_c - 0.3 * 0.05, abs=0.005)  # the same 15 mm behind on the unit circle


# --- parameter and config checks ---------------------------------------------------------------------------------

@pytest.mark.parametrize("key, value, words", [
    ("wheel_gain_right", 0.0, "m3pi.wheel_gain_right = 0.0: must be a finite number > 0"),
    ("wheel_gain_left", math.nan, "m3pi.wheel_gain_left = nan: must be a finite number > 0"),
    ("wheel_deadband", -0.01, "m3pi.wheel_deadband = -0.01: must be a finite number >= 0"),
    ("wheel_deadband", 1.0, "m3pi.wheel_deadband = 1.0: must be below m3pi.wheel_speed_max = 1.0"),
    ("command_latency", 1.5, "m3pi.command_latency = 1.5: must be a finite number >= 0 and <= 1"),
    ("pose_latency", -0.001, "m3pi.pose_latency = -0.001: must be a finite number >= 0 and <= 1"),
])
def test_fmu_parameters_of_an_impossible_robot_are_refused_by_name(key, value, words):
    errors = vehicle_parameter_errors(_values(**{key: value}))
    assert len(errors) == 1 and errors[0].startswith(words)


M3PI_PLATOON = {"platoon": {"count": 3, "dynamics": "m3pi", "speed": 0.3, "d_star": 0.6, "k_v": 2.0},
                "path": {"radius": 1.0}, "simulation": {"stop_time": 2.0, "step": 0.01, "max_substep": 0.005}}


def test_per_vehicle_robot_constants_override_the_m3pi_table():
    config = config_from_mapping({**M3PI_PLATOON, "m3pi": {"wheel_gain_right": 1.05, "command_latency": 0.02},
                                  "vehicles": {"2": {"m3pi": {"wheel_gain_right": 0.95, "pose_latency": 0.01}}}})
    params = [spec.parameters for spec in build_scenario(config).components[1:]]
    assert [p["m3pi.wheel_gain_right"] for p in params] == [1.05, 0.95, 1.05]
    assert [p["m3pi.pose_latency"] for p in params] == [0.0, 0.01, 0.0]
    assert all(p["m3pi.command_latency"] == 0.02 and p["m3pi.wheel_gain_left"] == 1.0 for p in params)
    assert "vehicle 1" in monolithic_refusal(config)
    assert monolithic_refusal(config_from_mapping({**M3PI_PLATOON, "m3pi": {"wheel_gain_left": 0.9}})) is None


@pytest.mark.parametrize("raw, words", [
    ({"m3pi": {"wheel_gain_left": 0.0}}, "m3pi.wheel_gain_left = 0.0"),
    ({"m3pi": {"command_latency": 2.0}}, "m3pi.command_latency = 2.0"),
    ({"vehicles": {"3": {"m3pi": {"pose_latency": -1.0}}}}, "vehicles.3.m3pi.pose_latency = -1.0"),
    ({"vehicles": {"2": {"m3pi": {"wheel_deadband": 0.5, "wheel_speed_max": 0.4}}}},
     "vehicles.2.m3pi.wheel_deadband = 0.5: expected below vehicle 2's wheel_speed_max = 0.4 m/s"),
    ({"vehicles": {"2": {"m3pi": {"lag": 0.1}}}}, "vehicles.2.m3pi.lag"),
    ({"vehicles": {"1": {"m3pi": {"motor_time_constant": 0.002}}}}, "vehicles.1.m3pi.motor_time_constant"),
])
def test_a_bad_robot_in_the_config_gets_one_line_naming_its_key(raw, words):
    with pytest.raises(ConfigError) as error:
        config_from_mapping({**M3PI_PLATOON, **raw})
    message = str(error.value)
    assert words in message and "\n" not in message


def test_latencies_that_keep_too_many_commands_in_flight_are_refused():
    with pytest.raises(ConfigError) as error:
        config_from_mapping({**M3PI_PLATOON, "simulation": {"stop_time": 1.0, "step": 0.001},
                             "m3pi": {"command_latency": 0.3}})
    assert "301 commands in flight at simulation.step = 0.001 s; a robot holds at most 256" in str(error.value)
    # the same latency at the paper's 10 ms step is fine, and any fraction of the step is
    config_from_mapping({**M3PI_PLATOON, "m3pi": {"command_latency": 0.3, "pose_latency": 0.0037}})
