"""The Vehicle FMU: trajectory shaping guidance plus kinematic or m3pi dynamics.

Inputs follow the paper's Fig. 2: the target's pose and speed come from the vehicle ahead (lateral
information flows backward); the speed and gap of the vehicle behind come from behind (velocity
information flows forward). Rates and sample times travel with them so the vehicle can extrapolate
its inputs inside a step (``coupling = "extrapolate"``).
"""

from __future__ import annotations

import math

from pythonfmu.default_experiment import DefaultExperiment

from fmus.model.dynamics import (M3PI_MOTOR_TIME_CONSTANT, M3PI_TRACK, M3PI_WHEEL_DEADBAND, M3PI_WHEEL_GAIN,
                                 M3PI_WHEEL_SPEED_MAX)
from fmus.model.factory import vehicle_parameter_errors, vehicle_stepper
from fmus.model.robot_loop import LATENCY_MAX, M3PI_COMMAND_LATENCY, M3PI_POSE_LATENCY
from fmus.model.vehicle import VEHICLE_INPUTS as _INPUT_ATTRIBUTES
from fmus.slaves import defaults as d
from fmus.slaves.base import PlatoonSlave, VariableInfo, real


STATE_OUTPUT = ()  # depends on no input: a function of the state alone


def _parameters() -> tuple[VariableInfo, ...]:
    return (
        VariableInfo("law", "String", "parameter", 'Guidance law: "sine" (paper eq. 5, exact on circles) or "regular" (eq. 2)', start="sine"),
        real("d_star", "parameter", "Desired spacing d*: the speed command V_cmd = V_follower d*/d_follower drives the follower's gap to it", "m", start=d.D_STAR, min=0.0),
        real("k_v", "parameter", "Speed loop gain: dV/dt = k_v (V_cmd - V)", "1/s", start=d.K_V, min=0.0),
        real("v_c", "parameter", "Commanded speed V_c, used when this vehicle is last in the platoon", "m/s", start=d.SPEED, min=0.0),
        VariableInfo("is_last", "Boolean", "parameter", "True for the last vehicle: it tracks V_c instead of the follower's spacing speed", start=True),
        VariableInfo("dynamics", "String", "parameter", 'Vehicle dynamics: "kinematic" (the paper\'s vehicle) or "m3pi" (differential drive)', start="kinematic"),
        VariableInfo("coupling", "String", "parameter", 'Inputs inside a step: "extrapolate" (arc for the target, rates for speed and gap; second order) or "hold" (zero-order hold)', start="extrapolate"),
        real("max_substep", "parameter", "Longest internal RK4 substep; a communication step is split into equal substeps no longer than this", "s", start=d.MAX_SUBSTEP, min=0.0),
        real("initial.x", "parameter", "Initial position, x", "m", start=d.VEHICLE_X),
        real("initial.y", "parameter", "Initial position, y", "m", start=d.VEHICLE_Y),
        real("initial.heading", "parameter", "Initial heading, counter-clockwise from the x axis", "rad", start=d.VEHICLE_HEADING),
        real("initial.speed", "parameter", "Initial speed", "m/s", start=d.VEHICLE_SPEED, min=0.0),
        real("m3pi.track", "parameter", "Distance W between the wheels (Pololu m3pi estimate; also used for the kinematic model's equivalent wheel speeds)", "m", start=M3PI_TRACK, min=0.0),
        real("m3pi.wheel_speed_max", "parameter", "Wheel speed limit (m3pi)", "m/s", start=M3PI_WHEEL_SPEED_MAX, min=0.0),
        real("m3pi.motor_time_constant", "parameter", "First-order motor lag of each wheel (m3pi)", "s", start=M3PI_MOTOR_TIME_CONSTANT, min=0.0),
    )


def _inputs() -> tuple[VariableInfo, ...]:
    return (
        real("target.x", "input", "Target position x (vehicle ahead, or the virtual target for vehicle 1)", "m", start=d.TARGET_X),
        real("target.y", "input", "Target position y", "m", start=d.TARGET_Y),
        real("target.heading", "input", "Target heading", "rad", start=d.TARGET_HEADING),
        real("target.speed", "input", "Target speed", "m/s", start=d.SPEED, min=0.0),
        real("target.speed_rate", "input", "Target speed rate dV/dt (for extrapolation)", "m/s2", start=0.0),
        real("target.turn_rate", "input", "Target heading rate (for arc extrapolation)", "rad/s", start=d.TARGET_TURN_RATE),
        real("target.time", "input", "Time the target values describe (the sender's output_time)", "s", start=0.0),
        real("follower.speed", "input", "Speed of the vehicle behind (unused when is_last)", "m/s", start=d.SPEED, min=0.0),
        real("follower.gap", "input", "Distance of the vehicle behind to this vehicle (unused when is_last)", "m", start=d.D_STAR, min=0.0),
        real("follower.speed_rate", "input", "Speed rate of the vehicle behind (for extrapolation)", "m/s2", start=0.0),
        real("follower.gap_rate", "input", "Rate of the gap of the vehicle behind (for extrapolation)", "m/s", start=0.0),
        real("follower.time", "input", "Time the follower values describe (the sender's output_time)", "s", start=0.0),
        real("disturbance.lateral_acceleration", "input", "Lateral acceleration added to the guidance command", "m/s2", start=0.0),
        real("disturbance.speed", "input", "Speed added over ground (an external push the speed loop does not see)", "m/s", start=0.0),
    )


def _outputs() -> tuple[VariableInfo, ...]:
    return (
        real("x", "output", "Position x", "m", depends_on=STATE_OUTPUT, initial_depends_on=("initial.x",)),
        real("y", "output", "Position y", "m", depends_on=STATE_OUTPUT, initial_depends_on=("initial.y",)),
        real("heading", "output", "Heading, counter-clockwise from the x axis (not wrapped)", "rad", depends_on=STATE_OUTPUT,
             initial_depends_on=("initial.heading",)),
        real("speed", "output", "Speed over ground", "m/s", initial_depends_on=("initial.speed", "disturbance.speed")),
        real("speed_rate", "output", "Rate of the speed over ground, dV/dt", "m/s2"),
        real("turn_rate", "output", "Heading rate", "rad/s"),
        real("lateral_acceleration", "output", "Lateral acceleration acting: guidance command plus disturbance", "m/s2"),
        real("gap", "output", "Distance d to this vehicle's target", "m"),
        real("gap_rate", "output", "Rate of the distance to the target, dd/dt", "m/s"),
        real("wheel.right", "output", "Right wheel speed (m3pi state; kinematic: eq. 10 equivalent)", "m/s"),
        real("wheel.left", "output", "Left wheel speed (m3pi state; kinematic: eq. 11 equivalent)", "m/s"),
        real("output_time", "output", "Time the outputs describe (the communication point they belong to); wire it to the receiver's *.time input", "s", depends_on=STATE_OUTPUT,
             initial_depends_on=(), depends_on_time=True),  # the (start) time: FMI 3.0's `time`, no variable in FMI 2.0
    )


def _speed_law_parameters() -> tuple[VariableInfo, ...]:
    """The speed laws beyond the paper's (docs/model.md, section 11): declared after the outputs, so that
    every variable the FMU had before keeps its value reference."""
    return (
        VariableInfo("speed_law", "String", "parameter", 'Speed law: "paper" (V_cmd = V_follower d*/d_follower, V_c when last), "acc" (constant time gap on the sensed gap) or "cacc" (Ploeg\'s, adapted: time gap plus the communicated target.speed)', start="paper"),
        real("time_gap", "parameter", "Time gap h of acc and cacc: desired gap standstill_gap + h V", "s", start=d.TIME_GAP, min=0.0),
        real("standstill_gap", "parameter", "Standstill gap r of acc and cacc: desired gap r + h V", "m", start=d.STANDSTILL_GAP, min=0.0),
        real("cacc_gain", "parameter", "Spacing-error gain k_p of cacc: the spacing error decays as de/dt = -k_p e", "1/s", start=d.CACC_GAIN, min=0.0),
    )


def _sensor_inputs() -> tuple[VariableInfo, ...]:
    """The on-board sensor of acc and cacc: the vehicle ahead's pose and motion, wired directly."""
    return (
        real("sensor.x", "input", "Position x of the vehicle ahead, from the on-board sensor (acc, cacc; wired directly, never through a link)", "m", start=d.TARGET_X),
        real("sensor.y", "input", "Position y of the vehicle ahead, from the on-board sensor (acc, cacc)", "m", start=d.TARGET_Y),
        real("sensor.heading", "input", "Heading of the vehicle ahead (sensor; to extrapolate its position)", "rad", start=d.TARGET_HEADING),
        real("sensor.speed", "input", "Speed of the vehicle ahead (sensor; to extrapolate its position)", "m/s", start=d.SPEED, min=0.0),
        real("sensor.speed_rate", "input", "Speed rate of the vehicle ahead (sensor; to extrapolate its position)", "m/s2", start=0.0),
        real("sensor.turn_rate", "input", "Heading rate of the vehicle ahead (sensor; to extrapolate its position)", "rad/s", start=d.TARGET_TURN_RATE),
        real("sensor.time", "input", "Time the sensor values describe (the sender's output_time)", "s", start=0.0),
    )


def _robot_parameters() -> tuple[VariableInfo, ...]:
    """A robot that is not its nominal model (docs/model.md): what `platoon calibrate` identifies. Declared last,
    so that every variable the FMU had before keeps its value reference; the defaults are the nominal robot,
    whose runs are the same to the bit as before these existed."""
    return (
        real("m3pi.wheel_gain_right", "parameter", "Right wheel speed per commanded speed (m3pi; a real motor's own gain)", "1", start=M3PI_WHEEL_GAIN, min=0.0),
        real("m3pi.wheel_gain_left", "parameter", "Left wheel speed per commanded speed (m3pi)", "1", start=M3PI_WHEEL_GAIN, min=0.0),
        real("m3pi.wheel_deadband", "parameter", "A wheel command smaller than this does not turn the wheel (m3pi; static friction)", "m/s", start=M3PI_WHEEL_DEADBAND, min=0.0),
        real("m3pi.command_latency", "parameter", "The radio: a wheel command acts this long after it is sent (m3pi; > 0 with pose_latency: the live run's sampled loop)", "s", start=M3PI_COMMAND_LATENCY, min=0.0, max=LATENCY_MAX),
        real("m3pi.pose_latency", "parameter", "The motion capture: the pose the controller sees, and the outputs, are this old (m3pi)", "s", start=M3PI_POSE_LATENCY, min=0.0, max=LATENCY_MAX),
    )


def _limit_parameters() -> tuple[VariableInfo, ...]:
    """The kinematic vehicle's optional speed limit (docs/model.md, section 6). Declared last, so that every
    variable the FMU had before keeps its value reference; the default 0 is no limit, the same to the bit as
    before it existed."""
    return (
        real("speed_max", "parameter", "Speed limit of the kinematic vehicle: its speed command is clipped to +-speed_max (0: no limit; an m3pi is bounded by m3pi.wheel_speed_max)", "m/s", start=0.0, min=0.0),
    )


class Vehicle(PlatoonSlave):
    """Platoon vehicle: trajectory shaping guidance (regular or sine) on kinematic or m3pi dynamics."""

    description = (
        "Platoon vehicle chasing its target with (modified) trajectory shaping guidance "
        "(Erekson, Sharma, Ratnoo, Gerdes: Multi-vehicle path following using modified trajectory shaping guidance)"
    )
    variables = (_parameters() + _inputs() + _outputs() + _speed_law_parameters() + _sensor_inputs() + _robot_parameters()
                 + _limit_parameters())
    input_attributes = _INPUT_ATTRIBUTES
    default_experiment = DefaultExperiment(start_time=0.0, stop_time=d.STOP_TIME, step_size=d.STEP)

    parameter_errors_of = staticmethod(vehicle_parameter_errors)
    stepper_of = staticmethod(vehicle_stepper)


assert set(_INPUT_ATTRIBUTES) == {i.name for i in _inputs() + _sensor_inputs()}
assert not any(math.isnan(i.start) for i in _inputs() + _sensor_inputs())
