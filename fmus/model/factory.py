"""From FMU parameter values (by their public names) to model objects.

The FMU slaves and the monolithic reference both build their models here, from the same dictionary
of parameter values, so a configuration means the same thing in every engine.
"""

from __future__ import annotations

import math
from typing import Any, Mapping

from .coupling import COUPLING_MODES
from .dynamics import DYNAMICS_KINDS, make_dynamics
from .guidance import LAWS, SPEED_LAWS
from .link import LinkParameters, LinkStepper
from .link import parameter_errors as _link_errors
from .paths import PATH_KINDS, make_path
from .robot_loop import LATENCY_MAX, RobotLoopStepper
from .target import VirtualTargetStepper
from .vehicle import SpeedLaw, VehicleModel, VehicleStepper


def _positive(values: Mapping[str, Any], names: tuple[str, ...]) -> list[str]:
    return [
        f"{name} = {values[name]}: must be a finite number > 0"
        for name in names
        if not (math.isfinite(values[name]) and values[name] > 0.0)
    ]


def _non_negative(values: Mapping[str, Any], names: tuple[str, ...]) -> list[str]:
    return [
        f"{name} = {values[name]}: must be a finite number >= 0"
        for name in names
        if not (math.isfinite(values[name]) and values[name] >= 0.0)
    ]


def _at_most(values: Mapping[str, Any], names: tuple[str, ...], limit: float) -> list[str]:
    return [f"{name} = {values[name]}: must be a finite number >= 0 and <= {limit:g}"
            for name in names if not (math.isfinite(values[name]) and 0.0 <= values[name] <= limit)]


# The parameters of a robot that is not its nominal model (docs/model.md, "A robot that is not its nominal model")
ROBOT_GAINS = ("m3pi.wheel_gain_right", "m3pi.wheel_gain_left")
ROBOT_LATENCIES = ("m3pi.command_latency", "m3pi.pose_latency")


def _robot_errors(values: Mapping[str, Any]) -> list[str]:
    """A wheel's gain is > 0 (a wheel that turns backwards or not at all is broken, not calibrated), its dead-band
    >= 0 and below the wheel speed limit (else no command would ever turn it), the latencies in [0, LATENCY_MAX]."""
    errors = _positive(values, ROBOT_GAINS) + _non_negative(values, ("m3pi.wheel_deadband",))
    errors += _at_most(values, ROBOT_LATENCIES, LATENCY_MAX)
    deadband, limit = values["m3pi.wheel_deadband"], values["m3pi.wheel_speed_max"]
    if not errors and math.isfinite(limit) and limit > 0.0 and deadband >= limit:  # a bad limit is its own error
        errors.append(f"m3pi.wheel_deadband = {deadband}: must be below m3pi.wheel_speed_max = {limit} (no "
                      "command would turn the wheels)")
    return errors


def _choice(values: Mapping[str, Any], name: str, allowed: tuple[str, ...]) -> list[str]:
    if values[name] in allowed:
        return []
    return [f"{name} = {values[name]!r}: expected one of {', '.join(allowed)}"]


def vehicle_parameter_errors(values: Mapping[str, Any]) -> list[str]:
    """Every reason these Vehicle parameters cannot run, as sentences naming the parameter."""
    return (
        _choice(values, "law", LAWS)
        + _choice(values, "speed_law", SPEED_LAWS)
        + _choice(values, "dynamics", DYNAMICS_KINDS)
        + _choice(values, "coupling", COUPLING_MODES)
        + _positive(
            values,
            ("d_star", "k_v", "v_c", "max_substep", "initial.speed", "m3pi.track", "m3pi.wheel_speed_max",
             "m3pi.motor_time_constant", "time_gap", "cacc_gain"),
        )
        + _non_negative(values, ("standstill_gap", "speed_max"))
        + _robot_errors(values)
    )


def target_parameter_errors(values: Mapping[str, Any]) -> list[str]:
    """Every reason these VirtualTarget parameters cannot run."""
    errors = (_choice(values, "path.kind", PATH_KINDS) + _choice(values, "coupling", COUPLING_MODES)
              + _choice(values, "speed_law", SPEED_LAWS))
    if values["path.direction"] not in (1, -1):
        errors.append(f"path.direction = {values['path.direction']}: expected 1 or -1")
    errors += _positive(values, ("d_star", "max_substep", "v_c"))
    if values["path.kind"] == "circle":
        errors += _positive(values, ("path.radius",))
        if not errors and values["d_star"] > 2.0 * values["path.radius"]:
            errors.append(
                f"d_star = {values['d_star']}: must be <= 2 R = {2.0 * values['path.radius']} (a chord of the circle)"
            )
    return errors


def controller_stepper(values: Mapping[str, Any], start_time: float) -> VehicleStepper:
    """The continuous vehicle of these parameters: the all-FMU model without latencies, and the controller a
    live run (bridge/live.py) keeps beside its robot, whatever the latencies."""
    dynamics = make_dynamics(
        values["dynamics"],
        values["k_v"],
        values["m3pi.track"],
        values["m3pi.wheel_speed_max"],
        values["m3pi.motor_time_constant"],
        values["m3pi.wheel_gain_right"],
        values["m3pi.wheel_gain_left"],
        values["m3pi.wheel_deadband"],
        values["speed_max"],
    )
    speed_law = SpeedLaw(values["speed_law"], values["time_gap"], values["standstill_gap"], values["cacc_gain"])
    model = VehicleModel(values["law"], values["d_star"], values["v_c"], bool(values["is_last"]), dynamics, speed_law)
    state = dynamics.initial_state(
        values["initial.x"], values["initial.y"], values["initial.heading"], values["initial.speed"]
    )
    return VehicleStepper(model, values["coupling"], values["max_substep"], state, start_time)


def samples_its_robot(values: Mapping[str, Any]) -> bool:
    """An m3pi with a radio or motion-capture latency: the sampled loop of a live run (fmus.model.robot_loop),
    not the continuous vehicle. Latencies of 0 are the continuous model, the same to the bit as before they
    existed."""
    return values["dynamics"] == "m3pi" and any(values[name] > 0.0 for name in ROBOT_LATENCIES)


def vehicle_stepper(values: Mapping[str, Any], start_time: float) -> VehicleStepper:
    """The Vehicle FMU's stepper: the continuous vehicle, or the sampled loop of a robot with latencies."""
    stepper = controller_stepper(values, start_time)
    if not samples_its_robot(values):
        return stepper
    return RobotLoopStepper(stepper.model, values["coupling"], values["max_substep"], stepper.state, start_time,
                            values["m3pi.command_latency"], values["m3pi.pose_latency"])


def target_path(values: Mapping[str, Any]):
    return make_path(
        values["path.kind"],
        values["path.radius"],
        values["path.x0"],
        values["path.y0"],
        values["path.heading"],
        int(values["path.direction"]),
    )


def target_stepper(values: Mapping[str, Any], start_time: float) -> VirtualTargetStepper:
    return VirtualTargetStepper(
        target_path(values),
        values["d_star"],
        values["coupling"],
        values["max_substep"],
        values["initial.arc_length"],
        start_time,
        values["speed_law"],
        values["v_c"],
    )


def link_parameters(values: Mapping[str, Any]) -> LinkParameters:
    return LinkParameters(values["delay"], values["jitter"], values["period"], values["loss"], values["burst"],
                          int(values["seed"]), int(values["stream"]))


def link_parameter_errors(values: Mapping[str, Any]) -> list[str]:
    """Every reason these Link parameters cannot run."""
    return _link_errors(link_parameters(values))


def link_stepper(values: Mapping[str, Any], start_time: float) -> LinkStepper:
    return LinkStepper(link_parameters(values), start_time)
