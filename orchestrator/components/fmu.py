"""Components the master steps: anything with named inputs and outputs that can advance in time.

``Component`` is the one interface the master loop knows; ``FmuComponent`` implements it on an FMI 2.0
co-simulation FMU through FMPy. A live endpoint (the Zenoh bridge) implements the same interface, so
it can stand in for a vehicle FMU without the master noticing.

FmuComponent keeps FMPy's bound fmi2 functions and preallocated ctypes arrays, so each step costs
one fmi2SetReal, one fmi2DoStep and one fmi2GetReal call and no per-call allocation.

FMPy is imported when first needed (``_fmpy``): the native engine steps FMUs without it, and an FMU
opened from the cache needs none of it either, so a native run does not pay for importing it (FMPy,
attrs, lxml: ~0.05 s of start-up, docs/performance.md "Whole runs").
"""

from __future__ import annotations

import shutil
import sys
from collections import deque
from ctypes import PYFUNCTYPE, byref, c_double, c_int, c_size_t, c_void_p, cast
from dataclasses import dataclass
from pathlib import Path
from functools import partial
from itertools import count
from struct import Struct
from typing import Any, Callable, Sequence

from types import SimpleNamespace

from fmus.errors import ComponentError  # noqa: F401  (re-exported: the engines raise it from here)
from fmus.component import Component  # noqa: F401  (re-exported: the interface FmuComponent implements)
from orchestrator.components import cache as fmu_cache
from orchestrator.components.cache import HeldFmu
from orchestrator.support.scratch import ScratchDir


# An fmi2 function returning fmi2Status, called with arguments that are already ctypes objects, holding
# the GIL (see FmuComponent._bind_hot_calls).
_RAW_FMI2_CALL = PYFUNCTYPE(c_int)


_RAW_CALLS: dict[int, Any] = {}

_FMI2_WARNING = 1  # fmi2Warning: a status above it is a failure (FMI 2.0, fmi2Status)
_WIRE_IS_NATIVE = sys.byteorder == "little"  # the served-FMU protocol's f64 are little-endian (bridge/fmu_wire.py)
_FMPY: SimpleNamespace | None = None


def _fmpy() -> SimpleNamespace:
    """What FmuComponent uses of FMPy, imported on first use (see the module's docstring)."""
    global _FMPY
    if _FMPY is None:
        from fmpy import calloc, free  # (fmpy.simulation re-exports them, at ~100 ms of imports)
        from fmpy.fmi1 import FMICallException
        from fmpy.fmi2 import (FMU2Slave, fmi2CallbackAllocateMemoryTYPE, fmi2CallbackFreeMemoryTYPE,
                               fmi2CallbackFunctions, fmi2CallbackLoggerTYPE, fmi2Real, fmi2True,
                               fmi2ValueReference)
        from fmpy.logging import addLoggerProxy

        _FMPY = SimpleNamespace(
            FMU2Slave=FMU2Slave, FMICallException=FMICallException, addLoggerProxy=addLoggerProxy,
            fmi2CallbackFunctions=fmi2CallbackFunctions, fmi2Real=fmi2Real, fmi2True=fmi2True,
            fmi2ValueReference=fmi2ValueReference, allocate=fmi2CallbackAllocateMemoryTYPE(calloc),
            free=fmi2CallbackFreeMemoryTYPE(free),
            logger=fmi2CallbackLoggerTYPE(_route_log),  # one callback object for the life of the process
        )
    return _FMPY


def _raw_fmi2_call(address: int) -> Any:
    """One ``_RAW_FMI2_CALL`` per function address: every instance of an FMU calls the same code (its
    library is loaded once per process), so all of them share one ctypes function object."""
    call = _RAW_CALLS.get(address)
    if call is None:
        call = _RAW_CALLS[address] = _RAW_FMI2_CALL(address)
    return call


def raw_call(slave: Any, name: str) -> Callable[..., int]:
    """The FMI function ``name`` of FMPy's ``slave`` as a ``_RAW_FMI2_CALL`` (FmuComponent._bind_hot_calls),
    or FMPy's wrapper returning the status where FMPy did not keep the function."""
    function = resolved_functions(slave).get(name)
    if function is None:
        return _status_returning(getattr(slave, name))
    return _raw_fmi2_call(cast(function, c_void_p).value)


def resolved_functions(slave: Any) -> dict[str, Any]:
    """The ctypes functions FMPy resolved from the FMU's library, by fmi2 name ({} if FMPy stops
    keeping them, and its wrappers stand in)."""
    return getattr(slave, "_functions", {})


# FMPy's addLoggerProxy keeps ONE logger per process (the last one registered) and hands it every
# message of every FMU instance. Each component's messages are told apart by the componentEnvironment
# it passes to fmi2Instantiate (a number of its own) and routed to its deque here; before, every
# message went to the component created last, and a failure of another one was reported without its
# reason ("fmi2DoStep failed with status 2").
_MESSAGES_BY_ENVIRONMENT: dict[int, deque[str]] = {}
_ENVIRONMENTS = count(1)


def _route_log(env: Any, instance: bytes, status: int, category: bytes, message: bytes) -> None:
    messages = _MESSAGES_BY_ENVIRONMENT.get(env or 0)
    if messages is not None:
        messages.append(message.decode("utf-8", "replace") if message else "")


def not_instantiated(*args: Any) -> int:
    raise RuntimeError("the FMU is not instantiated (initialize it first; a closed component cannot step)")


def _status_returning(method: Any) -> Any:
    """FMPy's wrapper of an fmi2 function, returning the status instead of raising on failure."""

    def call(*args: Any) -> int:
        try:
            method(*args)
        except _fmpy().FMICallException as error:
            return int(error.status)
        return 0

    return call


@dataclass
class UnpackedFmu:
    """An FMU extracted once; any number of instances share the folder.

    ``open`` extracts into a ``ScratchDir``: removed by ``cleanup``, and by the next run if this
    process is killed first. ``open_cached`` uses the per-user cache of extracted FMUs
    (orchestrator/components/cache.py) and only releases its hold on ``cleanup``.
    """

    path: Path
    directory: Path
    description: Any
    _owns_directory: bool = True
    _scratch: ScratchDir | None = None
    _held: HeldFmu | None = None

    @classmethod
    def open(cls, path: Path) -> "UnpackedFmu":
        from fmpy import extract, read_model_description

        scratch = ScratchDir(f"fmu-{Path(path).stem}")
        try:
            extract(str(path), str(scratch.path))
            description = read_model_description(str(path))
        except BaseException:
            scratch.remove()
            raise
        return cls(Path(path), scratch.path, description, True, scratch)

    @classmethod
    def open_cached(cls, path: Path) -> "UnpackedFmu":
        """``open``, from the cache of extracted FMUs: unzipped and checked against the FMI schema once
        per FMU file, its files checked against the zip's CRCs at every use; a private extraction
        (``open``) when the cache cannot serve (orchestrator/components/cache.py). ``description`` is then a
        ``fmu_cache.Description``: the fields of FMPy's that a run reads."""
        held = fmu_cache.hold(Path(path))
        if held is None:
            return cls.open(path)
        # as FMPy read it (and checked it against the FMI schema) when the entry was made: no FMPy now
        return cls(Path(path), held.directory, held.description, False, None, held)

    @property
    def guid(self) -> str:
        return self.description.guid

    def variables(self) -> dict[str, Any]:
        return {v.name: v for v in self.description.modelVariables}

    def start_values(self) -> dict[str, Any]:
        """Declared start values of parameters and inputs, typed."""
        values = {}
        for v in self.description.modelVariables:
            if v.causality in ("parameter", "input") and v.start is not None:
                values[v.name] = _typed(v.type, v.start)
        return values

    def cleanup(self) -> None:
        if self._held is not None:
            self._held.release()
        elif self._scratch is not None:
            self._scratch.remove()
        elif self._owns_directory:
            shutil.rmtree(self.directory, ignore_errors=True)


def _typed(kind: str, text: Any) -> Any:
    """A start value as the Python value of its FMI 2.0 or FMI 3.0 type."""
    if kind in ("Real", "Float64", "Float32"):
        return float(text)
    if kind == "Integer" or kind.startswith(("Int", "UInt")):
        return int(text)
    if kind == "Boolean":
        return text in (True, "true", "1", 1)
    return text


def parameters_by_type(variables: dict[str, Any], parameters: dict[str, Any]) -> dict[str, tuple[list[int], list[Any]]]:
    """Parameter value references and values grouped by FMI type, types in order of first appearance.

    Both engines set parameters in this order, which keeps their runs bit-identical.
    """
    groups: dict[str, tuple[list[int], list[Any]]] = {}
    for name, value in parameters.items():
        variable = variables[name]
        refs, values = groups.setdefault(variable.type, ([], []))
        refs.append(variable.valueReference)
        values.append(value)
    return groups


class FmuComponent:
    """One FMU instance behind the Component interface."""

    # named in failures (FMI 3.0: Fmu3Component)
    _SET_CALL, _GET_CALL, _STEP_CALL = "fmi2SetReal", "fmi2GetReal", "fmi2DoStep"

    def __init__(
        self, name: str, fmu: UnpackedFmu, parameters: dict[str, Any], inputs: list[str] | None = None
    ) -> None:
        self.name = name
        self.fmu = fmu
        variables = fmu.variables()
        unknown = sorted(set(parameters) - set(variables))
        if unknown:
            raise ValueError(f"{name}: {fmu.path.name} has no variable(s) {', '.join(unknown)}")
        self.parameters = parameters
        self.inputs = inputs if inputs is not None else [v.name for v in fmu.description.modelVariables if v.causality == "input"]
        starts = fmu.start_values()
        self.input_defaults = [float(starts[n]) for n in self.inputs]
        self.outputs = [v.name for v in fmu.description.modelVariables if v.causality == "output"]
        self._variables = variables
        self.messages: deque[str] = deque(maxlen=50)  # the latest FMU log lines, for error reports
        self._time = 0.0
        api = _fmpy()
        self._slave = self._open_slave()
        self._in_refs = (api.fmi2ValueReference * len(self.inputs))(*[variables[n].valueReference for n in self.inputs])
        self._in_values = (api.fmi2Real * len(self.inputs))()
        self._out_refs = (api.fmi2ValueReference * len(self.outputs))(*[variables[n].valueReference for n in self.outputs])
        self._out_values = (api.fmi2Real * len(self.outputs))()
        # Bulk copies between Python floats and the arrays, one C loop each way: struct packs the input
        # vector straight into the array's buffer, and a float64 view of the output array lists it
        # (ctypes' own slicing converts and checks element by element, several times slower).
        self._pack_inputs = Struct(f"{len(self.inputs)}d").pack_into
        self._output_view = memoryview(self._out_values).cast("B").cast("d")
        self._input_bytes = memoryview(self._in_values).cast("B")  # set_input_bytes copies into it
        self._instantiated = False
        self._set_real: Callable[[], int] = not_instantiated
        self._get_real: Callable[[], int] = not_instantiated
        self._do_step: Callable[[], int] = not_instantiated
        self._step_from, self._step_size = c_double(), c_double()  # fmi2DoStep's arguments, set per step

    def _open_slave(self) -> Any:
        """FMPy's slave of the FMU (not instantiated yet), its log routed to ``messages``."""
        api = _fmpy()
        slave = api.FMU2Slave(
            guid=self.fmu.guid,
            unzipDirectory=str(self.fmu.directory),
            modelIdentifier=self.fmu.description.coSimulation.modelIdentifier,
            instanceName=self.name,
        )
        self._callbacks = api.fmi2CallbackFunctions()
        self._environment = next(_ENVIRONMENTS)
        _MESSAGES_BY_ENVIRONMENT[self._environment] = self.messages
        self._callbacks.logger = api.logger
        self._callbacks.componentEnvironment = self._environment
        self._callbacks.allocateMemory = api.allocate
        self._callbacks.freeMemory = api.free
        api.addLoggerProxy(byref(self._callbacks))
        return slave

    def _bind_hot_calls(self) -> None:
        """fmi2SetReal, fmi2GetReal and fmi2DoStep with every argument but time bound once.

        The calls go to the functions FMPy resolved, through prototypes without argument types and
        with arguments already converted (the instance as ``c_void_p``, sizes as ``c_size_t``, the
        preallocated arrays): ctypes then passes them as they are, with no ``from_param`` conversion
        per argument and call, and no FMPy wrapper (a dict lookup, a logger test and a status test).
        The prototypes keep the GIL (``PYFUNCTYPE``), as the native core does: pythonfmu's wrapper
        takes it anyway to run the slave, so releasing it around the call only costs a release and a
        reacquire.
        The status is checked here instead, with FMPy's own exception. Falls back to FMPy's wrapper
        if FMPy ever stops keeping its functions in ``_functions``.
        """
        slave = self._slave
        raw = partial(raw_call, slave)
        instance = c_void_p(slave.component)
        self._set_real = partial(raw("fmi2SetReal"), instance, self._in_refs, c_size_t(len(self.inputs)),
                                 self._in_values)
        self._get_real = partial(raw("fmi2GetReal"), instance, self._out_refs, c_size_t(len(self.outputs)),
                                 self._out_values)
        self._do_step = partial(raw("fmi2DoStep"), instance, self._step_from, self._step_size, c_int(_fmpy().fmi2True))

    def _fail(self, error: Exception) -> ComponentError:
        reason = self.messages[-1] if self.messages else str(error)
        return ComponentError(self.name, self._time, reason)

    def initialize(self, start_time: float) -> None:
        """Instantiate, set up, apply parameters and enter initialization mode."""
        self._time = start_time
        slave = self._slave
        try:
            slave.instantiate(callbacks=self._callbacks, loggingOn=True)
            self._instantiated = True
            self._bind_hot_calls()
            slave.setupExperiment(startTime=start_time)
            self._set_parameters()
            slave.enterInitializationMode()
        except _fmpy().FMICallException as error:
            raise self._fail(error) from None
        except Exception as error:  # instantiation failure is a plain Exception in FMPy
            raise self._fail(error) from None

    def _set_parameters(self) -> None:
        by_type = parameters_by_type(self._variables, self.parameters)
        setters = {
            "Real": self._slave.setReal,
            "Integer": self._slave.setInteger,
            "Boolean": self._slave.setBoolean,
            "String": self._slave.setString,
        }
        for kind, (refs, values) in by_type.items():
            setters[kind](refs, values)

    def end_initialization(self) -> None:
        try:
            self._slave.exitInitializationMode()
        except _fmpy().FMICallException as error:
            raise self._fail(error) from None

    def set_inputs(self, values: Sequence[float]) -> None:
        self._pack_inputs(self._in_values, 0, *values)
        status = self._set_real()
        if status > _FMI2_WARNING:
            self._raise(self._SET_CALL, status)

    def get_outputs(self) -> list[float]:
        status = self._get_real()
        if status > _FMI2_WARNING:
            self._raise(self._GET_CALL, status)
        return self._output_view.tolist()

    def set_input_bytes(self, data: Any) -> None:
        """``set_inputs`` from the inputs packed as little-endian f64 (``data``: bytes or a memoryview), as a
        server receives them (bridge/fmu_wire.py): copied into the input array as they are, no Python float
        made on the way (the same doubles, bit for bit). ValueError when ``data`` is not one f64 per input."""
        if len(data) != 8 * len(self.inputs):
            raise ValueError(f"{len(data)} bytes of inputs, expected {len(self.inputs)} f64 ({8 * len(self.inputs)} bytes)")
        if _WIRE_IS_NATIVE:
            self._input_bytes[:] = data
        else:
            self._pack_inputs(self._in_values, 0, *Struct(f"<{len(self.inputs)}d").unpack(data))
        status = self._set_real()
        if status > _FMI2_WARNING:
            self._raise(self._SET_CALL, status)

    def output_bytes(self) -> bytes:
        """``get_outputs`` as little-endian f64 packed, as a server sends them (the array's bytes as they are)."""
        status = self._get_real()
        if status > _FMI2_WARNING:
            self._raise(self._GET_CALL, status)
        if _WIRE_IS_NATIVE:
            return bytes(self._out_values)
        return Struct(f"<{len(self.outputs)}d").pack(*self._output_view.tolist())

    def step(self, time: float, step: float) -> None:
        self._time = time
        self._step_from.value = time
        self._step_size.value = step
        status = self._do_step()
        if status > _FMI2_WARNING:
            self._raise(self._STEP_CALL, status)

    def _raise(self, function: str, status: int) -> None:
        """Fail a call whose status is above fmi2Warning, with the exception FMPy's wrapper would raise."""
        raise self._fail(_fmpy().FMICallException(function=function, status=status)) from None

    def close(self) -> None:
        if self._instantiated:
            try:
                self._slave.terminate()
            except _fmpy().FMICallException:
                pass
            # Free the instance but keep the shared library loaded: a pythonfmu binary leaves objects
            # in the host's interpreter, and unloading it (FMPy's freeInstance does) corrupts the heap
            # at interpreter exit. The library is loaded once per process anyway.
            self._slave.fmi2FreeInstance(self._slave.component)
            self._instantiated = False
            self._set_real = self._get_real = self._do_step = not_instantiated
        _MESSAGES_BY_ENVIRONMENT.pop(self._environment, None)
