"""What our two FMUs share on top of pythonfmu's Fmi2Slave.

pythonfmu registers variables but records no units, ranges or output dependencies. Here every
variable is declared once with all of that (``VariableInfo``); the builder turns the declarations
into a complete model description (``fmus.modeldescription``), and the slave uses them to store
values. Outputs are computed lazily from state and current inputs, and cached until an input or the
state changes, so a master may read them in any order, any number of times.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from pythonfmu import Fmi2Causality, Fmi2Slave, Fmi2Variability
from pythonfmu.enums import Fmi2Status
from pythonfmu.enums import Fmi2Initial
from pythonfmu.variables import Boolean, Integer, Real, String

from fmus.slaves.host_exit import guard_host_exit

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
    depends_on: tuple[str, ...] | None = None  # outputs: inputs they depend on directly

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


class PlatoonSlave(Fmi2Slave):
    """Base of the Vehicle and VirtualTarget slaves: declared variables, lazy outputs, FMU state."""

    variables: tuple[VariableInfo, ...] = ()
    author = "platoon-cosim"
    license = "MIT"

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
        if self._outputs is None:
            self._outputs = self.stepper.outputs() if self.stepper is not None else self._provisional_outputs()
        return self._outputs

    def _output(self, name: str) -> float:
        return self._current_outputs()[name]

    def get_real(self, vrs: list[int]) -> list[float]:
        """pythonfmu's get_real in one pass: outputs are computed at most once per change."""
        if not self._real_refs.issuperset(vrs):
            return super().get_real(vrs)  # raises pythonfmu's TypeError for the wrong type
        outputs = self._current_outputs()
        values = self.values
        names = [self._name_of[r] for r in vrs]
        return [float(outputs[n]) if n in outputs else float(values[n]) for n in names]

    def set_real(self, vrs: list[int], values: list[float]) -> None:
        """pythonfmu's set_real in one pass, forwarding inputs straight to the stepper."""
        if not self._settable_real_refs.issuperset(vrs):
            return super().set_real(vrs, values)
        store, stepper, attributes = self.values, self.stepper, self._input_attribute_of
        for reference, value in zip(vrs, values):
            store[self._name_of[reference]] = value
            if stepper is not None and reference in attributes:
                setattr(stepper, attributes[reference], float(value))
        self._outputs = None

    def _provisional_outputs(self) -> dict[str, float]:
        """Outputs during initialization mode, from the parameters and inputs set so far.

        Masters propagate initial values before the first step (libcosim runs start-up sweeps), so
        outputs must already mean something here. Values that cannot be computed yet read as NaN;
        invalid parameters are reported when initialization ends.
        """
        nan = {info.name: float("nan") for info in self.variables if info.causality == "output"}
        if self.parameter_errors():
            return nan
        stepper = self.make_stepper(getattr(self, "start_time", 0.0))
        try:
            for info in self.variables:
                if info.causality == "input":
                    self._apply_to(stepper, info.name, self.values[info.name])
            return stepper.outputs()
        except (ValueError, ZeroDivisionError, OverflowError):
            return nan

    # --- FMI life cycle -----------------------------------------------------------------------

    def setup_experiment(self, start_time: float, stop_time: float | None, tolerance: float | None) -> None:
        self.start_time = start_time

    def exit_initialization_mode(self) -> None:
        errors = self.parameter_errors()
        if errors:
            for error in errors:
                self.log(f"{self.instance_name}: invalid parameter {error}", Fmi2Status.error)
            raise ValueError(f"{self.instance_name}: invalid parameters: " + "; ".join(errors))
        self.stepper = self.make_stepper(getattr(self, "start_time", 0.0))
        for info in self.variables:
            if info.causality == "input":
                self.apply_input(info.name, self.values[info.name])
        self._outputs = None

    def do_step(self, current_time: float, step_size: float) -> bool:
        try:
            self.stepper.step(current_time, step_size)
        except (ValueError, ZeroDivisionError, OverflowError) as error:
            # Returning False (not raising) keeps the instance alive, so the logged reason reaches the
            # master; pythonfmu 0.7 destroys the slave on an exception before forwarding its log.
            self.log(f"{self.instance_name}: step from t = {current_time:.6g} s failed: {error}", Fmi2Status.error)
            return False
        self._outputs = None
        return True

    def parameter_errors(self) -> list[str]:
        raise NotImplementedError

    def make_stepper(self, start_time: float) -> Any:
        raise NotImplementedError

    # --- FMU state: everything that evolves, so get/set state restores a run exactly ------------

    def _get_fmu_state(self) -> dict[str, Any]:
        state = {"values": dict(self.values), "stepper": None}
        if self.stepper is not None:
            state["stepper"] = {k: (list(v) if isinstance(v, list) else v) for k, v in vars(self.stepper).items()
                                if isinstance(v, (int, float, list, bool))}
        return state

    def _set_fmu_state(self, state: dict[str, Any]) -> None:
        self.values = dict(state["values"])
        if state["stepper"] is not None:
            if self.stepper is None:
                self.stepper = self.make_stepper(state["stepper"]["time"])
            for key, value in state["stepper"].items():
                setattr(self.stepper, key, list(value) if isinstance(value, list) else value)
        self._outputs = None

