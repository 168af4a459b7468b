"""FMI 3.0 co-simulation FMUs behind the Component interface, and which FMUs a component can step.

``Fmu3Component`` is ``FmuComponent`` (orchestrator/components/fmu.py) on FMI 3.0: the same inputs and
outputs as f64 arrays, the same preallocated ctypes calls bound once (fmi3SetFloat64, fmi3DoStep,
fmi3GetFloat64), the same failures (a status above fmi3Warning raises ``ComponentError`` with the FMU's
last log line). FMI 3.0 differs where a host sees it: no setupExperiment (parameters are set on the
instantiated FMU, the start time goes to fmi3EnterInitializationMode), and fmi3DoStep can ask to end the
simulation or return early, both of which fail the step here, naming why (early return is never
allowed, event mode never used, so neither is part of a normal run).

``unsupported`` says, in one line, why an FMU cannot be stepped this way (model exchange only, FMI
1.0, inputs or outputs that are not one Float64 / Real each, clocks), so ``platoon serve`` refuses it
at its start instead of at a run's first request; ``fmu_component`` picks the class by FMI version.
"""

from __future__ import annotations

from ctypes import c_bool, c_double, c_size_t, c_void_p, pointer
from functools import partial
from typing import Any

from fmus.errors import ComponentError
from orchestrator.components.fmu import (FmuComponent, UnpackedFmu, not_instantiated, parameters_by_type,
                                         raw_call)

# What the wire carries: one 8-byte double per input and output (FMI 2.0 Real, FMI 3.0 Float64).
_FLOAT_TYPES = {"2.0": "Real", "3.0": "Float64"}
# Parameters by FMI 3.0 type: FMPy's setter of each (the values come as JSON: numbers, booleans, strings).
_SETTERS3 = {"Float64": "setFloat64", "Float32": "setFloat32", "Int8": "setInt8", "UInt8": "setUInt8",
             "Int16": "setInt16", "UInt16": "setUInt16", "Int32": "setInt32", "UInt32": "setUInt32",
             "Int64": "setInt64", "UInt64": "setUInt64", "Boolean": "setBoolean", "String": "setString"}


def unsupported(description: Any) -> str | None:
    """Why an FMU cannot be stepped as a component (None: it can). The reason names the FMI feature
    and, for a variable, its name and type."""
    version = str(getattr(description, "fmiVersion", ""))
    if version not in _FLOAT_TYPES:
        return f"FMI {version or '(no version)'}: only FMI 2.0 and 3.0 co-simulation FMUs are served"
    if getattr(description, "coSimulation", None) is None:
        kinds = [kind for kind, attribute in (("model exchange", "modelExchange"),
                                              ("scheduled execution", "scheduledExecution"))
                 if getattr(description, attribute, None) is not None]
        return (f"FMI {version} {' and '.join(kinds) or 'without co-simulation'} only: a served FMU must be "
                "co-simulation (it steps itself; no solver runs on the server)")
    wanted = _FLOAT_TYPES[version]
    for variable in description.modelVariables:
        if variable.causality not in ("input", "output"):
            if variable.type == "Clock":
                return f"clock {variable.name!r}: FMI 3.0 clocks (and the event mode they need) are not supported"
            continue
        if variable.type != wanted:
            return (f"{variable.causality} {variable.name!r} is {variable.type}: inputs and outputs must be "
                    f"{wanted} (each crosses the wire as one 8-byte double)")
        if getattr(variable, "dimensions", None):
            return f"{variable.causality} {variable.name!r} is an array: inputs and outputs must be scalars"
    return None


def fmu_component(name: str, fmu: UnpackedFmu, parameters: dict[str, Any]) -> FmuComponent:
    """The component of ``fmu``: FMI 2.0 or 3.0 (``unsupported`` first for anything else)."""
    problem = unsupported(fmu.description)
    if problem:
        raise ValueError(f"{fmu.path.name}: {problem}")
    cls = Fmu3Component if fmu.description.fmiVersion == "3.0" else FmuComponent
    return cls(name, fmu, parameters)


class Fmu3Component(FmuComponent):
    """One FMI 3.0 co-simulation instance behind the Component interface (module docstring)."""

    _SET_CALL, _GET_CALL, _STEP_CALL = "fmi3SetFloat64", "fmi3GetFloat64", "fmi3DoStep"

    def _open_slave(self) -> Any:
        from fmpy.fmi3 import FMU3Slave

        self._environment = None  # FMI 3.0 hands each instance its own log callback (``_log``)
        self._event_needed, self._terminate, self._early = c_bool(), c_bool(), c_bool()
        self._last_time = c_double()
        return FMU3Slave(guid=self.fmu.guid, unzipDirectory=str(self.fmu.directory),
                         modelIdentifier=self.fmu.description.coSimulation.modelIdentifier, instanceName=self.name)

    def _bind_hot_calls(self) -> None:
        """As ``FmuComponent._bind_hot_calls``, on fmi3SetFloat64, fmi3GetFloat64 and fmi3DoStep."""
        slave = self._slave
        raw = partial(raw_call, slave)
        instance = c_void_p(slave.component)
        self._set_real = partial(raw("fmi3SetFloat64"), instance, self._in_refs, c_size_t(len(self.inputs)),
                                 self._in_values, c_size_t(len(self.inputs)))
        self._get_real = partial(raw("fmi3GetFloat64"), instance, self._out_refs, c_size_t(len(self.outputs)),
                                 self._out_values, c_size_t(len(self.outputs)))
        self._do_step = partial(raw("fmi3DoStep"), instance, self._step_from, self._step_size, c_bool(True),
                                pointer(self._event_needed), pointer(self._terminate), pointer(self._early),
                                pointer(self._last_time))

    def initialize(self, start_time: float) -> None:
        """Instantiate (no event mode, no early return), set the parameters, enter initialization at ``start_time``."""
        from fmpy.fmi1 import FMICallException

        self._time = start_time
        slave = self._slave
        try:
            slave.instantiate(loggingOn=True, logMessage=self._log)
            self._instantiated = True
            self._bind_hot_calls()
            self._set_parameters()
            slave.enterInitializationMode(startTime=start_time)
        except FMICallException as error:
            raise self._fail(error) from None
        except Exception as error:  # instantiation failure is a plain Exception in FMPy
            raise self._fail(error) from None

    def _log(self, environment: Any, status: int, category: bytes, message: bytes) -> None:
        """fmi3LogMessageCallback (FMPy wraps it, and keeps the wrapper while the slave lives)."""
        self.messages.append(message.decode("utf-8", "replace") if message else "")

    def _set_parameters(self) -> None:
        """By type, in the order FMI 2.0 components set theirs (``parameters_by_type``)."""
        for kind, (refs, values) in parameters_by_type(self._variables, self.parameters).items():
            setter = _SETTERS3.get(kind)
            if setter is None:
                raise ValueError(f"{self.name}: parameters of type {kind} cannot be set from a run")
            getattr(self._slave, setter)(refs, values)

    def step(self, time: float, step: float) -> None:
        super().step(time, step)
        if self._terminate.value:
            raise ComponentError(self.name, time, "fmi3DoStep: the FMU asked to end the simulation")
        if self._early.value:
            raise ComponentError(self.name, time, f"fmi3DoStep returned early at t = {self._last_time.value:.6g} s, "
                                 "though early return was not allowed")

    def close(self) -> None:
        if self._instantiated:
            from fmpy.fmi1 import FMICallException

            try:
                self._slave.terminate()
            except FMICallException:
                pass
            self._slave.fmi3FreeInstance(self._slave.component)  # the library stays loaded (see FmuComponent.close)
            self._instantiated = False
            self._set_real = self._get_real = self._do_step = not_instantiated
