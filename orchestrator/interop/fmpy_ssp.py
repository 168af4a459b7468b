"""Run an exported SSP package (`platoon export-ssp`) in FMPy's own SSP runner
(``fmpy.ssp.simulation.simulate_ssp``, FMPy 0.3.32), with the fixes it needs: ``simulate_ssp`` here.

A supported helper of the package, not a test aid: FMPy is what a user most likely has at hand to run
an SSP, and as is its runner cannot run ours (docs/fmus.md, "Run the whole platoon in another tool",
"In FMPy"; tests/test_ssp.py checks this against our own run, and notices when FMPy fixes it itself).

As is, simulate_ssp cannot run the platoon:

1. it reads the components' ParameterBindings (``read_ssd`` parses the .ssv files) but never applies
   them: only its own ``parameter_set`` argument is applied, and that one cannot set a String
   (``set_value`` raises "Unsupported type: String"; ``law``, ``dynamics``, ``coupling`` and
   ``path.kind`` are Strings);
2. every connector starts at 0.0 and the first step's inputs are those zeros: a gap of 0 m divides
   by zero in the VirtualTarget (V_0 = V_1 d*/d_1) and the first fmi2DoStep fails;
3. an input connector that no connection reaches (``disturbance.*``) is wired to the source of the
   previous input's connection (``fmpy.ssp.ssd.get_connections`` reuses its loop variable): each
   vehicle's ``disturbance.speed`` would follow its follower's ``time``.

It also instantiates every FMU with logging off (``loggingOn=False``), so an FMU's reason for a failed
call (a remote vehicle's server gone, naming the vehicle and the server) never reaches the user: only
``fmi2DoStep failed with status 2``.

The fixes replace three of its module functions: ``set_parameters`` turns each FMU's logging on (FMPy
prints its messages) and applies each component's own bindings with the setter of each parameter's type, ``get_connections`` keeps only the pairs the .ssd
connects, and the first ``do_step`` first moves every component's initial outputs along the
connections until they settle (what our master and libcosim do before the first step). ``stop_time`` is passed half a step short: simulate_ssp adds the step to its
clock (``time += step_size``) and steps while ``time < stop_time``, so the rounded sum could add a step.
"""

from __future__ import annotations

import fmpy.ssp.simulation as fmpy_ssp
from fmpy.ssp.ssd import Component

_SETTERS = {"Real": ("setReal", float), "Integer": ("setInteger", int),
            "Boolean": ("setBoolean", lambda text: text == "true"), "String": ("setString", str)}


def apply_bindings(component: Component, _parameter_set: object) -> None:
    """The component's ParameterBindings (as read_ssd parsed them), each value with its type's setter; first,
    the FMU's logging on (every category), so FMPy prints what it says."""
    component.fmu.setDebugLogging(True, [])
    for binding in component.parameterBindings:
        for parameter_set in binding.parameterValues:
            for parameter in parameter_set.parameters:
                setter, convert = _SETTERS[parameter.type]
                reference = component.variables[parameter.name].valueReference
                getattr(component.fmu, setter)([reference], [convert(parameter.value)])


def simulate_ssp(package: str, stop_time: float, step_size: float):
    """``fmpy.ssp.simulation.simulate_ssp`` with the bindings applied and the connectors started from the
    components' initial outputs; its result array (a row per step, columns ``<component>.<connector>``)."""
    connections: list = []
    original_get_connections, original_do_step, original_set_parameters = (
        fmpy_ssp.get_connections, fmpy_ssp.do_step, fmpy_ssp.set_parameters)
    started = []

    def get_connections(system, connectors=None):
        declared = {(c.startElement, c.startConnector, c.endElement, c.endConnector) for c in system.connections}
        connections[:] = [(start, end) for start, end in original_get_connections(system, connectors)
                          if (start.parent.name, start.name, end.parent.name, end.name) in declared]
        return connections

    def do_step(component, time, step):
        if not started:
            started.append(True)
            components = {end.parent for _, end in connections} | {start.parent for start, _ in connections}
            for _ in range(len(components) + 2):  # sweeps, as many as the longest chain of direct feedthrough
                for start, end in connections:
                    end.value = fmpy_ssp.get_value(start.parent, start.name)
                for other in components:
                    for connector in other.connectors:
                        if connector.kind == "input" and hasattr(connector, "value"):
                            fmpy_ssp.set_value(other, connector.name, connector.value)
        original_do_step(component, time, step)

    fmpy_ssp.get_connections, fmpy_ssp.do_step, fmpy_ssp.set_parameters = get_connections, do_step, apply_bindings
    try:
        return fmpy_ssp.simulate_ssp(package, stop_time=stop_time - step_size / 2, step_size=step_size,
                                     parameter_set=True)  # not None: makes simulate_ssp call set_parameters
    finally:
        fmpy_ssp.get_connections, fmpy_ssp.do_step, fmpy_ssp.set_parameters = (
            original_get_connections, original_do_step, original_set_parameters)
