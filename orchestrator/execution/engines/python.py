"""The python engine: the master loop in Python (orchestrator/execution/python_master.py) over FMUs
opened with FMPy's bindings, live robots on Zenoh, or remote vehicles (FMUs in a `platoon serve`,
docs/remote.md); the only engine that steps live robots, paced to the wall clock when one is in the run,
and remote vehicles."""

from __future__ import annotations

from typing import ClassVar

from fmus.component import Component
from fmus.realtime import Pacer, PacingPriority
from orchestrator.components.fmu import FmuComponent
from orchestrator.components.live import live_component
from orchestrator.components.remote import remote_components
from orchestrator.execution.engine import Check, EngineSetup
from orchestrator.execution.python_master import Master
from orchestrator.observers.base import Observers


class Engine:
    name: ClassVar[str] = "python"

    def __init__(self, setup: EngineSetup) -> None:
        sim = setup.config.simulation
        self.step = sim.step
        remote = remote_components(setup.config, setup.scenario, setup.fmus)  # in a `platoon serve` elsewhere
        self.components: list[Component] = [
            live_component(spec, setup.fmus[spec.fmu], setup.config, index) if spec.name in setup.live
            else remote[spec.name] if spec.name in remote
            else FmuComponent(spec.name, setup.fmus[spec.fmu], spec.parameters)
            for index, spec in enumerate(setup.scenario.components)
        ]
        # with a live robot the run is paced to the wall clock (the robot cannot run faster)
        self.pacer = Pacer() if setup.live else None
        self.master = Master(self.components, setup.scenario.connections, setup.scenario.schedules, sim.master,
                             pacer=self.pacer)
        self.priority: PacingPriority | None = None

    @property
    def time(self) -> float:
        return self.master.time

    def start(self, observers: Observers, check: Check) -> None:
        observers.point(0.0, self.master.initialize(0.0))
        check()
        if self.pacer is not None:  # the robots are there: from here this thread keeps the wall-clock schedule
            self.priority = PacingPriority("the run's stepping thread")
            if self.priority.note is not None:
                observers.log(0.0, self.priority.level, self.priority.note)

    def advance(self, steps: int, observers: Observers, check: Check) -> None:
        def observe(t: float, outputs: list[list[float]]) -> None:
            observers.point(t, outputs)
            check()

        self.master.advance(self.step, observe, steps, tick=observers.advanced)

    def close(self) -> None:
        if self.priority is not None:  # the schedule is over: stopping the robots and finalizing need no priority
            self.priority.restore()
        self.master.close()
