"""The floor, and the bare FMPy loop: one Jacobi loop in Python over per-component set/step/get calls.

``DirectLoop`` steps any list of components given as bound methods (set inputs, step, get outputs):
our FMUs' pythonfmu slave classes called directly (``SlavePlatoon``, the floor: no master can step
our FMUs for less) or FMPy's ``FMU2Slave`` (the bare FMPy loop, engines.py). One loop for both, so
that the two differ only in what they call: the FMI boundary.
"""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any, Callable, Sequence

from fmus.builders import DEFAULT_OUT

from orchestrator.components.fmu import parameters_by_type
from .platoon import STEP, causal_names, final_positions, routes_of, scenario_for, unpacked_fmus

ORDERS = ("phases", "per-component")


class DirectLoop:
    """Jacobi steps over components given as bound ``set(refs, values)``, ``step(t, h)``, ``get(refs)``.

    A step returning ``False`` is a failure (the slave classes' convention; FMPy raises instead).
    """

    def __init__(self, setters: Sequence[Callable], steppers: Sequence[Callable], getters: Sequence[Callable],
                 in_refs: list[list[int]], out_refs: list[list[int]], inputs: list[list[float]],
                 routes: list[list[tuple[int, int, int]]], names: list[str]) -> None:
        self.setters, self.steppers, self.getters = list(setters), list(steppers), list(getters)
        self.in_refs, self.out_refs, self.inputs, self.routes, self.names = in_refs, out_refs, inputs, routes, names
        self.outputs = [get(refs) for get, refs in zip(self.getters, out_refs)]
        self.k = 0

    def settle(self) -> None:
        """The settle sweeps every master here runs in initialization mode (at most N + 2)."""
        count = len(self.setters)
        for _ in range(count + 2):
            changed = False
            for c in range(count):
                for i, source, o in self.routes[c]:
                    self.inputs[c][i] = self.outputs[source][o]
                self.setters[c](self.in_refs[c], self.inputs[c])
                fresh = self.getters[c](self.out_refs[c])
                changed |= fresh != self.outputs[c]
                self.outputs[c] = fresh
            if not changed:
                break

    def refresh(self) -> None:
        self.outputs = [get(refs) for get, refs in zip(self.getters, self.out_refs)]

    def run(self, steps: int, order: str = "phases") -> None:
        """``steps`` Jacobi steps. ``order="phases"``: set every input, step every component, get every
        output (Master.step). ``"per-component"``: every input transferred first, then per component
        set, step and get back to back; the same calls per component, so the same results."""
        setters, steppers, getters = self.setters, self.steppers, self.getters
        inputs, routes, in_refs, out_refs = self.inputs, self.routes, self.in_refs, self.out_refs
        count = len(setters)
        outputs = self.outputs
        per_component = order == "per-component"
        for k in range(self.k, self.k + steps):
            t = k * STEP
            h = (k + 1) * STEP - t
            for c in range(count):
                vector = inputs[c]
                for i, source, o in routes[c]:
                    vector[i] = outputs[source][o]
                if not per_component:
                    setters[c](in_refs[c], vector)
            if per_component:
                fresh = []
                for c in range(count):
                    setters[c](in_refs[c], inputs[c])
                    if steppers[c](t, h) is False:
                        raise RuntimeError(f"{self.names[c]}: step failed at t = {t}")
                    fresh.append(getters[c](out_refs[c]))
                outputs = fresh
            else:
                for c in range(count):
                    if steppers[c](t, h) is False:
                        raise RuntimeError(f"{self.names[c]}: step failed at t = {t}")
                outputs = [getters[c](out_refs[c]) for c in range(count)]
        self.outputs = outputs
        self.k += steps

    def run_split(self, steps: int) -> dict[str, float]:
        """The phases loop, each call timed separately: seconds in transfer, set, step and get; per
        component in ``self.spent_by_component`` (set + step + get of each component)."""
        clock = time.perf_counter
        setters, steppers, getters = self.setters, self.steppers, self.getters
        inputs, routes, in_refs, out_refs = self.inputs, self.routes, self.in_refs, self.out_refs
        count = len(setters)
        outputs = self.outputs
        spent = dict.fromkeys(("transfer", "set_real", "do_step", "get_real"), 0.0)
        mine = self.spent_by_component = [0.0] * count
        for k in range(self.k, self.k + steps):
            t = k * STEP
            h = (k + 1) * STEP - t
            for c in range(count):
                a = clock()
                vector = inputs[c]
                for i, source, o in routes[c]:
                    vector[i] = outputs[source][o]
                b = clock()
                setters[c](in_refs[c], vector)
                e = clock()
                spent["transfer"] += b - a
                spent["set_real"] += e - b
                mine[c] += e - b
            for c in range(count):
                a = clock()
                steppers[c](t, h)
                e = clock()
                spent["do_step"] += e - a
                mine[c] += e - a
            fresh = []
            for c in range(count):
                a = clock()
                fresh.append(getters[c](out_refs[c]))
                e = clock()
                spent["get_real"] += e - a
                mine[c] += e - a
            outputs = fresh
        self.outputs = outputs
        self.k += steps
        return spent

    def finals(self, out_names: dict[str, list[str]]) -> dict[str, list[float]]:
        return final_positions(self.names, [dict(zip(out_names[name], values))
                                            for name, values in zip(self.names, self.outputs)])


class SlavePlatoon(DirectLoop):
    """The floor: the pythonfmu slave classes of our FMUs, instantiated, initialized and stepped directly."""

    def __init__(self, n: int, steps: int, coupling: str = "extrapolate", fmu_dir: Path = DEFAULT_OUT) -> None:
        from fmus.slaves.Vehicle import Vehicle
        from fmus.slaves.VirtualTarget import VirtualTarget

        classes = {"Vehicle": Vehicle, "VirtualTarget": VirtualTarget}
        self.scenario = scenario = scenario_for(n, steps, coupling)
        fmus = unpacked_fmus(fmu_dir)
        self.slaves: list[Any] = []
        in_refs, out_refs, inputs = [], [], []
        in_names: dict[str, list[str]] = {}
        self.out_names: dict[str, list[str]] = {}
        for spec in scenario.components:
            fmu = fmus[spec.fmu]
            slave = classes[spec.fmu](instance_name=spec.name, resources=str(fmu.directory / "resources"))
            refs = {variable.name: vr for vr, variable in slave.vars.items()}
            in_names[spec.name] = causal_names(fmu, "input")
            self.out_names[spec.name] = causal_names(fmu, "output")
            in_refs.append([refs[v] for v in in_names[spec.name]])
            out_refs.append([refs[v] for v in self.out_names[spec.name]])
            starts = fmu.start_values()
            inputs.append([float(starts[v]) for v in in_names[spec.name]])
            slave.setup_experiment(0.0, None, None)
            setters = {"Real": slave.set_real, "Integer": slave.set_integer, "Boolean": slave.set_boolean,
                       "String": slave.set_string}
            variables = fmu.variables()
            for kind, (_, values) in parameters_by_type(variables, spec.parameters).items():
                names = [name for name in spec.parameters if variables[name].type == kind]
                setters[kind]([refs[name] for name in names], values)
            slave.enter_initialization_mode()
            self.slaves.append(slave)
        slaves = self.slaves
        super().__init__([s.set_real for s in slaves], [s.do_step for s in slaves], [s.get_real for s in slaves],
                         in_refs, out_refs, inputs, routes_of(scenario, in_names, self.out_names),
                         [s.name for s in scenario.components])
        self.settle()
        for slave in slaves:
            slave.exit_initialization_mode()
        self.refresh()

    def finals(self, out_names: dict[str, list[str]] | None = None) -> dict[str, list[float]]:
        return super().finals(out_names or self.out_names)
