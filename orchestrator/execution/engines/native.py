"""The native engine: the same master loop in C (orchestrator/execution/native), over the FMUs'
shared libraries; it hands the observers blocks of rows already decimated to the trace's rate, and
records nothing when no observer wants rows."""

from __future__ import annotations

from typing import ClassVar

from orchestrator.execution.engine import Check, EngineSetup
from orchestrator.execution.native import NativeComponent, NativeMaster
from orchestrator.observers.base import Observers
from orchestrator.trace.format import FLUSH_INTERVAL

# s of wall time after which a partial block goes to the observers anyway: a trace on disk never lags far behind
DELIVER_INTERVAL = FLUSH_INTERVAL / 2


class Engine:
    name: ClassVar[str] = "native"

    def __init__(self, setup: EngineSetup) -> None:
        sim = setup.config.simulation
        self.step, self.every, self.rows_per_block = sim.step, sim.trace_every, setup.block
        components = [NativeComponent(spec.name, setup.fmus[spec.fmu], spec.parameters)
                      for spec in setup.scenario.components]
        self.master = NativeMaster(components, setup.scenario.connections, setup.scenario.schedules, sim.master)

    @property
    def time(self) -> float:
        return self.master.time

    def start(self, observers: Observers, check: Check) -> None:
        self.master.initialize(0.0)  # the initial point opens the first block

    def advance(self, steps: int, observers: Observers, check: Check) -> None:
        deliver_interval, call_steps = observers.delivery(self.step, DELIVER_INTERVAL, None)
        self.master.run_blocks(self.step, steps, observers.block if observers.wants_rows else None, every=self.every,
                               block=self.rows_per_block, check=check, initialize=False, tick=observers.advanced,
                               deliver_interval=deliver_interval, call_steps=call_steps)

    def close(self) -> None:
        self.master.close()
