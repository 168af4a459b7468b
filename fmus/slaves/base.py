"""What our two FMUs share on top of pythonfmu's Fmi2Slave.

pythonfmu registers variables but records no units, ranges or output dependencies. Here every
variable is declared once with all of that (``VariableInfo``); the builder turns the declarations
into a complete model description (``fmus.modeldescription.fmi2``), and the slave uses them to store
values. Outputs are computed lazily from state and current inputs, and cached until an input or the
state changes, so a master may read them in any order, any number of times.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass
from typing import Any, Callable, Mapping

from pythonfmu import Fmi2Causality, Fmi2Slave, Fmi2Variability
from pythonfmu.enums import Fmi2Status
from pythonfmu.enums import Fmi2Initial
from pythonfmu.variables import Boolean, Integer, Real, String

from fmus.model.integrate import substep_count
from fmus.slaves.host_exit import guard_host_exit
from fmus.slaves.refusal import fmi_call, fmi_step, keep_module_globals, refuse

_TYPES = {"Real": Real, "Integer": Integer, "Boolean": Boolean, "String": String}


@dataclass(frozen=True)
class VariableInfo:
    """One FMU variable, everything a model description says about it."""

    name: str
    type: str  # "Real" | "Integer" | "Boolean" | "String"
    causality: str  # "parameter" | "input" | "output"
    description: str
    unit: str | None = None
    start: Any = None
    min: float | None = None
    max: float | None = None
    variability: str | None = None  # default: parameters fixed, inputs/outputs continuous (Real)
    depends_on: tuple[str, ...] | None = None  # outputs: inputs they depend on directly (None: all)
    # Outputs: the inputs and parameters their value in Initialization Mode is computed from
    # (ModelStructure/InitialUnknowns, see fmus.modeldescription.fmi2); None: all of them.
    initial_depends_on: tuple[str, ...] | None = None
    # Outputs with ``depends_on``: the parameters their value at a communication point is computed
    # from besides the state (FMI 3.0 counts parameters and time among the knowns there, FMI 2.0 only
    # inputs and states; see fmus.modeldescription.fmi3), and whether it is a function of time itself.
    parameter_dependencies: tuple[str, ...] = ()
    depends_on_time: bool = False

    @property
    def resolved_variability(self) -> str:
        if self.variability is not None:
            return self.variability
        if self.causality == "parameter":
            return "fixed"
        return "continuous" if self.type == "Real" else "discrete"


def real(name: str, causality: str, description: str, unit: str | None, **kw: Any) -> VariableInfo:
    return VariableInfo(name, "Real", causality, description, unit, **kw)


_Tables = tuple[dict[int, str], frozenset[int], frozenset[int], dict[int, str]]
_TABLES: dict[type, _Tables] = {}


def _shared_tables(cls: type[PlatoonSlave], name_of: dict[int, str]) -> _Tables:
    """The hot-path lookup tables of ``cls``: name by value reference, the Real references, the
    settable Real references and the stepper attribute of each input. Built by the first instance;
    an instance whose variables differ (never expected) gets its own."""
    tables = _TABLES.get(cls)
    if tables is not None and tables[0] == name_of:
        return tables
    kinds = {info.name: info for info in cls.variables}
    real_refs = frozenset(r for r, n in name_of.items() if kinds[n].type == "Real")
    settable = frozenset(r for r in real_refs if kinds[name_of[r]].causality != "output")
    attributes = {r: cls.input_attributes[n] for r, n in name_of.items() if kinds[n].causality == "input"}
    tables = (name_of, real_refs, settable, attributes)
    _TABLES.setdefault(cls, tables)
    return tables


# Every method pythonfmu's binary calls on a slave, but do_step (see fmus.slaves.refusal).
FMI_METHODS = ("setup_experiment", "enter_initialization_mode", "exit_initialization_mode", "terminate",
               "get_real", "get_integer", "get_boolean", "get_string", "set_real", "set_integer", "set_boolean",
               "set_string", "_get_fmu_state", "_set_fmu_state")


class PlatoonSlave(Fmi2Slave):
    """Base of the Vehicle and VirtualTarget slaves: declared variables, lazy outputs, FMU state."""

    variables: tuple[VariableInfo, ...] = ()
    author = "platoon-cosim"
    license = "MIT"

    def __init_subclass__(cls, **kwargs: Any) -> None:
        super().__init_subclass__(**kwargs)
        keep_module_globals(cls)  # see fmus.slaves.refusal: pythonfmu's fmi2Instantiate releases them
        # A subclass's own FMI methods get the same guard as ours: no exception reaches the binary raw.
        for name in FMI_METHODS:
            method = cls.__dict__.get(name)
            if method is not None and not hasattr(method, "__wrapped__"):
                setattr(cls, name, fmi_call(method))
        step = cls.__dict__.get("do_step")
        if step is not None and not hasattr(step, "__wrapped__"):
            cls.do_step = fmi_step(step)

    def __init__(self, **kwargs: Any) -> None:
        super().__init__(**kwargs)
        guard_host_exit(kwargs.get("resources"), type(self).__name__)
        self.values: dict[str, Any] = {}
        self._outputs: dict[str, float] | None = None
        self.stepper: Any = None
        for info in self.variables:
            self._declare(info)
        # Lookup tables for the hot path (get_real/set_real are called every step by every master).
        # Every instance of a class declares the same variables in the same order, so the tables are
        # equal; all instances share one copy, which stays in cache however many vehicles step.
        name_of = {reference: variable.name for reference, variable in self.vars.items()}
        self._name_of, self._real_refs, self._settable_real_refs, self._input_attribute_of = _shared_tables(
            type(self), name_of)

    def _declare(self, info: VariableInfo) -> None:
        name = info.name
        causality = getattr(Fmi2Causality, info.causality)
        variability = getattr(Fmi2Variability, info.resolved_variability)
        if info.causality == "output":
            self.values[name] = 0.0
            getter = lambda: self._output(name)  # noqa: E731 - closure per variable
            variable = _TYPES[info.type](
                name,
                causality=causality,
                variability=variability,
                initial=Fmi2Initial.calculated,
                description=info.description,
                getter=getter,
            )
        else:
            self.values[name] = info.start
            variable = _TYPES[info.type](
                name,
                start=info.start,
                causality=causality,
                variability=variability,
                description=info.description,
                getter=lambda: self.values[name],
                setter=lambda value: self._set(name, value),
            )
        self.register_variable(variable, nested=False)

    def _set(self, name: str, value: Any) -> None:
        self.values[name] = value
        self._outputs = None
        if self.stepper is not None:
            self.apply_input(name, value)

    input_attributes: dict[str, str] = {}

    def apply_input(self, name: str, value: Any) -> None:
        """Forward an input to the stepper."""
        self._apply_to(self.stepper, name, value)

    def _apply_to(self, stepper: Any, name: str, value: Any) -> None:
        setattr(stepper, self.input_attributes[name], float(value))

    def _current_outputs(self) -> dict[str, float]:
        """The outputs, computed once per change; refuses the call if any of them is not finite
        (a host must never read NaN or inf with fmi2OK)."""
        if self._outputs is None:
            try:
                outputs = self.stepper.outputs() if self.stepper is not None else self._provisional_outputs()
            except (ValueError, ZeroDivisionError, OverflowError) as error:  # e.g. a vehicle on its target
                refuse(self, f"{self.instance_name}: the outputs at t = {self._time():.6g} s cannot be computed "
                             f"({type(error).__name__}: {error})")
            not_finite = _not_finite(outputs)
            if not_finite:
                refuse(self, f"{self.instance_name}: output(s) {not_finite} not finite at t = "
                             f"{self._time():.6g} s; check the inputs")
            self._outputs = outputs
        return self._outputs

    def _output(self, name: str) -> float:
        return self._current_outputs()[name]

    def _time(self) -> float:
        return self.stepper.time if self.stepper is not None else getattr(self, "start_time", 0.0)

    @fmi_call
    def get_real(self, vrs: list[int]) -> list[float]:
        """pythonfmu's get_real in one pass: outputs are computed at most once per change."""
        self._refuse_if_failed()
        if not self._real_refs.issuperset(vrs):
            return super().get_real(vrs)  # raises pythonfmu's TypeError for the wrong type
        outputs = self._current_outputs()
        values = self.values
        names = [self._name_of[r] for r in vrs]
        return [float(outputs[n]) if n in outputs else float(values[n]) for n in names]

    @fmi_call
    def set_real(self, vrs: list[int], values: list[float]) -> None:
        """pythonfmu's set_real in one pass, forwarding inputs straight to the stepper. A value that
        is not finite is refused before anything is stored."""
        self._refuse_if_failed()
        if not self._settable_real_refs.issuperset(vrs):
            return super().set_real(vrs, values)
        if not all(map(math.isfinite, values)):
            bad = ", ".join(f"{self._name_of[r]} = {v}" for r, v in zip(vrs, values) if not math.isfinite(v))
            refuse(self, f"{self.instance_name}: refused {bad}: values must be finite")
        store, stepper, attributes = self.values, self.stepper, self._input_attribute_of
        for reference, value in zip(vrs, values):
            store[self._name_of[reference]] = value
            if stepper is not None and reference in attributes:
                setattr(stepper, attributes[reference], float(value))
        self._outputs = None

    @fmi_call
    def get_integer(self, vrs: list[int]) -> list[int]:
        self._refuse_if_failed()
        return super().get_integer(vrs)

    @fmi_call
    def get_boolean(self, vrs: list[int]) -> list[bool]:
        self._refuse_if_failed()
        return super().get_boolean(vrs)

    @fmi_call
    def get_string(self, vrs: list[int]) -> list[str]:
        self._refuse_if_failed()
        return super().get_string(vrs)

    @fmi_call
    def set_integer(self, vrs: list[int], values: list[int]) -> None:
        self._refuse_if_failed()
        super().set_integer(vrs, values)

    @fmi_call
    def set_boolean(self, vrs: list[int], values: list[bool]) -> None:
        self._refuse_if_failed()
        super().set_boolean(vrs, values)

    @fmi_call
    def set_string(self, vrs: list[int], values: list[str]) -> None:
        self._refuse_if_failed()
        super().set_string(vrs, values)

    def _provisional_outputs(self) -> dict[str, float]:
        """Outputs during initialization mode, from the parameters and inputs set so far.

        Masters propagate initial values before the first step (libcosim runs start-up sweeps), so
        outputs must already mean something here. While the parameters are invalid there are no
        outputs: reading them is refused with the reasons (the same ones exitInitializationMode
        gives), never answered with NaN.
        """
        errors = self.parameter_errors()
        if errors:
            refuse(self, f"{self.instance_name}: no outputs while parameters are invalid: " + "; ".join(errors))
        stepper = self.make_stepper(getattr(self, "start_time", 0.0))
        for info in self.variables:
            if info.causality == "input":
                self._apply_to(stepper, info.name, self.values[info.name])
        return stepper.outputs()

    # --- FMI life cycle -----------------------------------------------------------------------

    _failure: str | None = None  # why this instance can no longer work (invalid parameters)

    def _refuse_if_failed(self) -> None:
        if self._failure is not None:
            refuse(self, f"{self.instance_name}: refused, the instance failed: {self._failure}")

    @fmi_call
    def setup_experiment(self, start_time: float, stop_time: float | None, tolerance: float | None) -> None:
        self._refuse_if_failed()
        if not math.isfinite(start_time):
            refuse(self, f"{self.instance_name}: start time {start_time} is not finite")
        self.start_time = start_time

    @fmi_call
    def enter_initialization_mode(self) -> None:
        self._refuse_if_failed()

    @fmi_call
    def exit_initialization_mode(self) -> None:
        """Build the stepper, or fail for good with every invalid parameter named in one refusal;
        every later call on this instance is then refused with the same reasons."""
        self._refuse_if_failed()
        errors = self.parameter_errors()
        if errors:
            self._failure = "invalid parameter(s): " + "; ".join(errors)
            refuse(self, f"{self.instance_name}: {self._failure}")
        self.stepper = self.make_stepper(getattr(self, "start_time", 0.0))
        for info in self.variables:
            if info.causality == "input":
                self.apply_input(info.name, self.values[info.name])
        self._outputs = None

    @fmi_call
    def terminate(self) -> None:
        """Always allowed, also on a failed instance: hosts terminate whatever happened."""

    def do_step(self, current_time: float, step_size: float) -> bool:
        """One communication step, or fmi2Discard (False) with the reason logged and the instance
        left exactly as it was before the call (so the master may retry, roll back or stop).

        Refused: a step before initialization or after a failure, a time or step size that is not a
        finite number, a step size <= 0 (FMI 2.0, section 4.2.2: communicationStepSize > 0; the
        Reference FMUs answer fmi2Error too), a step that needs more than ``MAX_SUBSTEPS_PER_STEP``
        RK4 substeps (so fmi2DoStep(t, 1e9) answers at once instead of running for days), and a
        step whose new state or outputs are not finite. Never raises: the binary maps an exception
        to fmi2Fatal, a False to fmi2Discard (see ``refusal``).
        """
        try:
            reason = self._step(current_time, step_size)
        except Exception as error:  # noqa: BLE001 - a failed step is a Discard, never a crash
            reason = f"{type(error).__name__}: {error}"
        if reason is None:
            return True
        self.log(f"{self.instance_name}: step from t = {current_time:.6g} s by h = {step_size:.6g} s "
                 f"refused: {reason}", Fmi2Status.error)
        return False

    MAX_SUBSTEPS_PER_STEP = 100_000

    def _step(self, current_time: float, step_size: float) -> str | None:
        """The step; returns why it was refused, or None once it was taken."""
        if self._failure is not None:
            return f"the instance failed: {self._failure}"
        if self.stepper is None:
            return "the instance is not initialized (call fmi2ExitInitializationMode first)"
        if not (math.isfinite(current_time) and math.isfinite(step_size)):
            return "time and step size must be finite numbers"
        if step_size <= 0.0:
            return "the step size must be > 0"
        substeps = substep_count(step_size, self.stepper.max_substep)
        if substeps > self.MAX_SUBSTEPS_PER_STEP:
            return (f"it needs {substeps:.3g} RK4 substeps of at most max_substep = {self.stepper.max_substep:g} s; "
                    f"the limit is {self.MAX_SUBSTEPS_PER_STEP} per step (h <= "
                    f"{self.MAX_SUBSTEPS_PER_STEP * self.stepper.max_substep:g} s)")
        before = dict(vars(self.stepper))
        try:
            self.stepper.step(current_time, step_size)
            outputs = self.stepper.outputs()
        except Exception:
            vars(self.stepper).update(before)
            raise
        not_finite = _not_finite(outputs)
        if not_finite:
            vars(self.stepper).update(before)
            return f"output(s) {not_finite} would not be finite; check the inputs"
        self._outputs = outputs
        return None

    # Each model names its two factory functions (fmus.model.factory), pure functions of the
    # parameter values, so a state's own values can rebuild its stepper.
    parameter_errors_of: Callable[[Mapping[str, Any]], list[str]]
    stepper_of: Callable[[Mapping[str, Any], float], Any]

    def parameter_errors(self) -> list[str]:
        return type(self).parameter_errors_of(self.values)

    def make_stepper(self, start_time: float) -> Any:
        return type(self).stepper_of(self.values, start_time)

    # --- FMU state: everything that evolves, so get/set state restores a run exactly ------------
    #
    # A state carries the parameter values it was taken with, and setting it rebuilds the stepper
    # from them: the stepper caches its model (law, d*, dynamics) when built, so copying only the
    # evolving numbers into an instance created with other parameters would replay the old
    # trajectory with the new parameters (tests/test_hostile_fmus.py holds it).

    @fmi_call
    def _get_fmu_state(self) -> dict[str, Any]:
        self._refuse_if_failed()
        state = {"model": type(self).__name__, "values": dict(self.values), "stepper": None}
        if self.stepper is not None:
            state["stepper"] = {k: (list(v) if isinstance(v, list) else v) for k, v in vars(self.stepper).items()
                                if isinstance(v, (int, float, list, bool))}
        return state

    @fmi_call
    def _set_fmu_state(self, state: Any) -> None:
        self._refuse_if_failed()
        problem = self._state_problem(state)
        if problem:
            refuse(self, f"{self.instance_name}: refused the FMU state: {problem}")
        values = dict(state["values"])
        stepper = None
        if state["stepper"] is not None:
            stepper = self._restored_stepper(values, state["stepper"])
        self.values, self.stepper, self._outputs = values, stepper, None

    def _state_problem(self, state: Any) -> str | None:
        if not isinstance(state, dict) or "unreadable" in state:
            return state.get("unreadable", "not a state") if isinstance(state, dict) else "not a state"
        if state.get("model") != type(self).__name__:
            return f"it is a state of {state.get('model')!r}, not of {type(self).__name__}"
        if not isinstance(state.get("values"), dict) or set(state["values"]) != set(self.values):
            return "its variables are not this model's"
        return None

    def _restored_stepper(self, values: dict[str, Any], numbers: dict[str, Any]) -> Any:
        """A stepper built from the state's own parameters, then given the state's evolving numbers."""
        errors = type(self).parameter_errors_of(values)
        if errors:
            refuse(self, f"{self.instance_name}: refused the FMU state: its parameters are invalid: "
                         + "; ".join(errors))
        stepper = type(self).stepper_of(values, numbers["time"])
        for key, value in numbers.items():
            setattr(stepper, key, list(value) if isinstance(value, list) else value)
        return stepper

    @staticmethod
    def _fmu_state_from_bytes(state: bytes) -> dict[str, Any]:
        """Never raises: the binary calls it on the class, and an exception here would drop its
        reference to whichever instance it serves (see ``refusal``). Garbage becomes a state that
        ``_set_fmu_state`` refuses with the reason."""
        try:
            return json.loads(state.decode("utf-8"))
        except Exception as error:  # noqa: BLE001
            return {"unreadable": f"the serialized state cannot be read ({type(error).__name__}: {error})"}


def _not_finite(outputs: dict[str, float]) -> str:
    """The names (and values) of the outputs that are not finite, or ''."""
    if all(map(math.isfinite, outputs.values())):
        return ""
    return ", ".join(f"{name} = {value}" for name, value in outputs.items() if not math.isfinite(value))
