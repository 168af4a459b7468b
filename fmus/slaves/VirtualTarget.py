"""The VirtualTarget FMU: the point on the path that the lead vehicle chases.

It knows the path and moves along it at V_0 = V_1 d*/d_1 (paper eq. 3), from the lead vehicle's
speed V_1 and distance d_1 (velocity information flowing forward); under acc and cacc at V_c. A
``disturbance.speed`` input adds a push to that speed.
"""

from __future__ import annotations

from pythonfmu.default_experiment import DefaultExperiment

from fmus.model.factory import target_parameter_errors, target_stepper
from fmus.slaves import defaults as d
from fmus.slaves.base import PlatoonSlave, VariableInfo, real

_INPUT_ATTRIBUTES = {
    "lead.speed": "lead_speed",
    "lead.gap": "lead_gap",
    "lead.speed_rate": "lead_speed_rate",
    "lead.gap_rate": "lead_gap_rate",
    "lead.time": "lead_time",
    "disturbance.speed": "added_speed",
}

STATE_OUTPUT = ()
# What the target's place on its path is computed from at the start.
PATH = ("path.kind", "path.radius", "path.x0", "path.y0", "path.heading", "path.direction")
PLACE = PATH + ("initial.arc_length",)
# What the curvature is computed from (and, with the arc length, the pose at a communication point).
CURVATURE = ("path.kind", "path.radius", "path.direction")


class VirtualTarget(PlatoonSlave):
    """Virtual target moving along a circle or a line at the lead vehicle's spacing speed."""

    description = "Virtual target on the path for the lead vehicle of a trajectory-shaping platoon"
    variables = (
        VariableInfo("path.kind", "String", "parameter", 'Path shape: "circle" or "line"', start="circle"),
        real("path.radius", "parameter", "Circle radius R", "m", start=d.RADIUS, min=0.0),
        real("path.x0", "parameter", "Circle centre x, or a point of the line", "m", start=0.0),
        real("path.y0", "parameter", "Circle centre y, or a point of the line", "m", start=0.0),
        real("path.heading", "parameter", "Line direction, or the angle of the circle's s = 0 point seen from its centre", "rad", start=0.0),
        VariableInfo("path.direction", "Integer", "parameter", "Circle travel direction: 1 counter-clockwise, -1 clockwise", start=1, min=-1, max=1),
        real("initial.arc_length", "parameter", "Initial arc length s along the path", "m", start=0.0),
        real("d_star", "parameter", "Desired distance d* of the lead vehicle", "m", start=d.D_STAR, min=0.0),
        VariableInfo("coupling", "String", "parameter", 'Inputs inside a step: "extrapolate" (rates; second order) or "hold" (zero-order hold)', start="extrapolate"),
        real("max_substep", "parameter", "Longest internal RK4 substep", "s", start=d.MAX_SUBSTEP, min=0.0),
        real("lead.speed", "input", "Lead vehicle speed V_1", "m/s", start=d.SPEED, min=0.0),
        real("lead.gap", "input", "Lead vehicle distance d_1 to this target", "m", start=d.D_STAR, min=0.0),
        real("lead.speed_rate", "input", "Lead vehicle speed rate (for extrapolation)", "m/s2", start=0.0),
        real("lead.gap_rate", "input", "Rate of the lead vehicle's gap (for extrapolation)", "m/s", start=0.0),
        real("lead.time", "input", "Time the lead values describe (the lead's output_time)", "s", start=0.0),
        real("x", "output", "Target position x", "m", depends_on=STATE_OUTPUT, initial_depends_on=PLACE,
             parameter_dependencies=PATH),
        real("y", "output", "Target position y", "m", depends_on=STATE_OUTPUT, initial_depends_on=PLACE,
             parameter_dependencies=PATH),
        real("heading", "output", "Path tangent heading at the target", "rad", depends_on=STATE_OUTPUT,
             initial_depends_on=PLACE, parameter_dependencies=PATH),
        real("speed", "output", "Target speed V_0 = V_1 d*/d_1 (acc, cacc: v_c), plus disturbance.speed", "m/s"),
        real("speed_rate", "output", "Rate of the target speed", "m/s2"),
        real("turn_rate", "output", "Heading rate V_0 times curvature", "rad/s"),
        real("curvature", "output", "Signed path curvature at the target", "1/m", depends_on=STATE_OUTPUT,
             initial_depends_on=CURVATURE, parameter_dependencies=CURVATURE),
        real("arc_length", "output", "Arc length s travelled along the path", "m", depends_on=STATE_OUTPUT,
             initial_depends_on=("initial.arc_length",)),
        real("output_time", "output", "Time the outputs describe (the communication point they belong to); wire it to the receiver's target.time input", "s", depends_on=STATE_OUTPUT,
             initial_depends_on=(), depends_on_time=True),  # the (start) time: FMI 3.0's `time`, no variable in FMI 2.0
        # the speed laws beyond the paper's, last: every earlier variable keeps its value reference
        VariableInfo("speed_law", "String", "parameter", 'The lead vehicle\'s speed law: "paper" (the target moves at V_1 d*/d_1) or "acc"/"cacc" (it moves at the constant v_c)', start="paper"),
        real("v_c", "parameter", "Commanded speed V_c: the target's speed under acc and cacc", "m/s", start=d.SPEED, min=0.0),
        # a speed push on the platoon's head (after the laws' variables: every earlier one keeps its reference)
        real("disturbance.speed", "input", "Speed added to the target's (a prescribed push on the platoon's head)", "m/s",
             start=0.0),
    )
    input_attributes = _INPUT_ATTRIBUTES
    default_experiment = DefaultExperiment(start_time=0.0, stop_time=d.STOP_TIME, step_size=d.STEP)

    parameter_errors_of = staticmethod(target_parameter_errors)
    stepper_of = staticmethod(target_stepper)
