"""The monolithic engine: no FMU is stepped; the whole platoon is one system integrated by one RK4
(fmus/model/platoon.py), with the same steppers and parameter values the FMUs would hold. It has no
coupling error, so it is the yardstick of the co-simulation (``platoon run --compare-monolithic``).
Like the co-simulation, it records at every communication point and takes the disturbances there."""

from __future__ import annotations

from typing import ClassVar

from fmus.errors import ComponentError
from fmus.model.factory import target_stepper, vehicle_stepper
from fmus.model.platoon import PlatoonSystem
from orchestrator.execution.engine import Check, EngineSetup
from orchestrator.observers.base import Observers
from orchestrator.scenario.scenario import monolithic_refusal

NAME = "platoon (monolithic)"  # what a failure names as the component


def monolithic_system(setup: EngineSetup) -> PlatoonSystem:
    """The same steppers the FMUs would hold, from the same parameter values (FMU defaults + config)."""
    refusal = monolithic_refusal(setup.config)
    if refusal is not None:
        raise ComponentError(NAME, 0.0, refusal)
    steppers = []
    for spec in setup.scenario.components:
        values = {**setup.fmus[spec.fmu].start_values(), **spec.parameters}
        steppers.append(target_stepper(values, 0.0) if spec.fmu == "VirtualTarget" else vehicle_stepper(values, 0.0))
    return PlatoonSystem(steppers[0], steppers[1:])


class Engine:
    name: ClassVar[str] = "monolithic"

    def __init__(self, setup: EngineSetup) -> None:
        self.sim = setup.config.simulation
        self.schedules = setup.scenario.schedules
        names = [spec.name for spec in setup.scenario.components]
        self.order = [setup.outputs[name] for name in names]
        self.target, self.vehicles = names[0], names[1:]
        self.system = monolithic_system(setup)
        self.state: list[float] = []
        self.time = 0.0

    def _set_disturbances(self, t: float) -> None:
        """Every component's pushes at t (summed where several hit one input), held over the step."""
        values = {name: [0.0, 0.0] for name in [self.target] + self.vehicles}
        for schedule in self.schedules:
            slot = 0 if schedule.input.endswith("lateral_acceleration") else 1
            values[schedule.component][slot] += schedule.value_at(t)
        self.system.set_disturbances([tuple(values[name]) for name in self.vehicles], values[self.target][1])

    def _record(self, observers: Observers) -> None:
        rows = self.system.outputs(self.time, self.state)
        observers.point(self.time, [[row[key] for key in keys] for row, keys in zip(rows, self.order)])

    def start(self, observers: Observers, check: Check) -> None:
        try:
            self.state = self.system.initial_state()
            self._set_disturbances(0.0)
            self._record(observers)
        except (ValueError, ZeroDivisionError, OverflowError) as failure:
            raise ComponentError(NAME, self.time, str(failure)) from None
        check()

    def advance(self, steps: int, observers: Observers, check: Check) -> None:
        step, system = self.sim.step, self.system
        t = 0.0
        try:
            for k in range(steps):
                t, t_next = k * step, (k + 1) * step
                self._set_disturbances(t)
                self.state = system.advance(t, self.state, t_next - t, self.sim.max_substep)
                self.time = t_next
                self._record(observers)
                check()
                observers.advanced(k + 1)
        except (ValueError, ZeroDivisionError, OverflowError) as failure:  # named at the step's start
            raise ComponentError(NAME, t, str(failure)) from None

    def close(self) -> None:
        pass
