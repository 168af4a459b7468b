"""The native engine: the master's hot loop in C (``orchestrator/execution/native/_core.c``), same results as Master.

``NativeMaster`` has Master's interface (``initialize``, ``step``, ``run``, ``close``; ``outputs``,
``time``, ``components``) and gives bit-identical outputs at every communication point, because the C
core does exactly what Master and FmuComponent do: the same FMI calls in the same order with the same
arguments (t_k = t0 + k h, h_k = t_(k+1) - t_k), the same settle sweeps in initialization mode, the
same transfer (connected inputs, then pulses zeroed and summed, sampled at t_k). What differs is that
the loop, the transfers and the copies into the trace buffer are C, and Python sees the run once per
block of steps:

* ``run(stop_time, step, observer, steps, ...)`` calls ``observer(t, outputs)`` at every
  communication point like Master.run (so ``run_scenario``'s observer works unchanged), from rows the
  C loop filled for a block of steps;
* ``run_blocks(step, steps, sink, every=..., block=...)`` hands ``sink`` a ``RowBlock`` of float64 rows
  ``[t, every output of every component]`` per block (decimated ``every`` steps in C), so a trace
  writer can encode whole blocks off the hot loop.

A failing FMU raises ``orchestrator.components.fmu.ComponentError`` naming the component, the time and
the reason (the FMU's last log line), after every row completed before the failure was delivered.
The C core holds the GIL: pythonfmu FMUs run their Python model in this interpreter.
"""

from __future__ import annotations

import time as clock
from array import array
from dataclasses import dataclass
from typing import Any, Callable, Sequence

from orchestrator.components.fmu import ComponentError, UnpackedFmu, parameters_by_type
from orchestrator.execution.python_master import MASTERS, Observer, check_finite, resolve_routes
from orchestrator.scenario.scenario import TIME_TOLERANCE, ScheduledInput
from orchestrator.scenario.wiring import Connection
from orchestrator.support.rows import RowBlock, float_buffer

try:
    from orchestrator.execution.native import _core
except ImportError as _error:  # not built (no C compiler at install time, or not Linux)
    _core = None
    IMPORT_ERROR: str | None = str(_error)
else:
    IMPORT_ERROR = None

BLOCK = 256  # steps per return to Python in run() (observer path)
TRACE_BLOCK = 500  # rows per block in run_blocks(), as the trace writer's block
CALL_STEPS = 64  # steps per call into C when blocks are also delivered on a wall-time interval

Sink = Callable[[RowBlock], None]


def available() -> bool:
    """True when the C extension is built and importable."""
    return _core is not None


@dataclass
class NativeComponent:
    """An FMU instance the native core will create: what FmuComponent knows, without loading FMPy's slave.

    The same constructor arguments as FmuComponent, and the same ``inputs``, ``outputs`` and
    ``input_defaults`` (the model description's causalities and start values, in its order).
    """

    name: str
    fmu: UnpackedFmu
    parameters: dict[str, Any]
    inputs: list[str] | None = None

    def __post_init__(self) -> None:
        variables = self.fmu.variables()
        unknown = sorted(set(self.parameters) - set(variables))
        if unknown:
            raise ValueError(f"{self.name}: {self.fmu.path.name} has no variable(s) {', '.join(unknown)}")
        described = self.fmu.description.modelVariables
        if self.inputs is None:
            self.inputs = [v.name for v in described if v.causality == "input"]
        starts = self.fmu.start_values()
        self.input_defaults = [float(starts[n]) for n in self.inputs]
        self.outputs = [v.name for v in described if v.causality == "output"]
        self._variables = variables

    def library(self) -> str:
        identifier = self.fmu.description.coSimulation.modelIdentifier
        return str(self.fmu.directory / "binaries" / "linux64" / f"{identifier}.so")

    def resource_uri(self) -> str:
        return (self.fmu.directory / "resources").as_uri()  # what FMPy's instantiate passes

    def parameter_groups(self) -> list[tuple[str, list[int], list[Any]]]:
        """Parameters by type, in the order FmuComponent sets them."""
        groups = parameters_by_type(self._variables, self.parameters)
        return [(kind, refs, values) for kind, (refs, values) in groups.items()]

    def refs(self, names: Sequence[str]) -> list[int]:
        return [self._variables[n].valueReference for n in names]


def _as_native(component: Any) -> NativeComponent:
    if isinstance(component, NativeComponent):
        return component
    # an FmuComponent, or anything with the same constructor attributes
    return NativeComponent(component.name, component.fmu, dict(component.parameters), list(component.inputs))


class NativeMaster:
    """Master's interface on the C core. ``components``: NativeComponents (or FmuComponent-like specs)."""

    def __init__(
        self,
        components: Sequence[Any],
        connections: Sequence[Connection],
        schedules: Sequence[ScheduledInput] = (),
        algorithm: str = "jacobi",
    ) -> None:
        if _core is None:
            raise RuntimeError(f"the native engine is not built ({IMPORT_ERROR}); reinstall with a C compiler "
                               "(pip install -e .) or use the Python engine")
        if algorithm not in MASTERS:
            raise ValueError(f"unknown master {algorithm!r}; expected one of {', '.join(MASTERS)}")
        self.components = [_as_native(c) for c in components]
        self.algorithm = algorithm
        offsets, total = [], 0
        for component in self.components:
            offsets.append(total)
            total += len(component.outputs)
        self._slices = [(offset, offset + len(c.outputs)) for offset, c in zip(offsets, self.components)]
        self.width = 1 + total
        routes = resolve_routes(self.components, connections, schedules)  # Master's checks and messages
        connected = [[(inp, offsets[source] + out) for inp, source, out in r.connected] for r in routes]
        scheduled = [
            [(inp, float(s.start), float(s.duration), float(s.value), TIME_TOLERANCE, float(s.frequency))
             for inp, s in r.scheduled]
            for r in routes
        ]
        description = [
            (c.name, c.library(), c.fmu.guid, c.resource_uri(), c.refs(c.inputs), c.refs(c.outputs),
             list(c.input_defaults), c.parameter_groups(), connected[i], scheduled[i])
            for i, c in enumerate(self.components)
        ]
        self._core = _core.Core(description, algorithm, ComponentError)
        self.time = 0.0

    # --- Master's interface ----------------------------------------------------------------------

    @property
    def outputs(self) -> list[list[float]]:
        return self._core.outputs()

    def messages(self, component: int | str) -> list[str]:
        """The latest log lines of a component (its FMU's logger), oldest first."""
        if isinstance(component, str):
            component = [c.name for c in self.components].index(component)
        return self._core.messages(component)

    def initialize(self, start_time: float = 0.0) -> list[list[float]]:
        """Instantiate, set parameters, settle initial outputs in initialization mode, leave it."""
        self.time = start_time
        self._core.initialize(float(start_time))
        outputs = self._core.outputs()
        check_finite(self.components, outputs, start_time)
        return outputs

    def step(self, step: float) -> list[list[float]]:
        """One step from ``time`` (not advanced, as in Master.step)."""
        self._core.step(float(self.time), float(step))
        return self._core.outputs()

    def run(self, stop_time: float, step: float, observer: Observer, steps: int, start_time: float = 0.0,
            tick: Callable[[int], None] | None = None, block: int = BLOCK) -> None:
        """Initialize and run ``steps`` steps, calling ``observer(t, outputs)`` at every point (Master.run)."""
        observer(start_time, self.initialize(start_time))
        width = self.width
        buffer = float_buffer(min(block, steps) or 1, width)
        slices = self._slices
        k = 0
        while k < steps:
            stop = min(steps, k + block)
            try:
                self._core.run(float(start_time), float(step), k, stop, buffer, 1, 0)
            finally:
                # rows completed before a failure are observed first, as Master observed each step
                done = self._core.rows_done
                for j, row in enumerate(RowBlock(buffer[:done * width], width).tolist()):
                    self.time = row[0]
                    observer(row[0], [row[1 + a:1 + b] for a, b in slices])
                    if tick is not None:
                        tick(k + j + 1)
            k = stop

    def run_blocks(self, step: float, steps: int, sink: Sink | None, every: int = 1, block: int = TRACE_BLOCK,
                   start_time: float = 0.0, tick: Callable[[int], None] | None = None,
                   initialize: bool = True, check: Callable[[], object] | None = None,
                   deliver_interval: float | None = None, call_steps: int | None = None) -> None:
        """Initialize and run ``steps`` steps; ``sink(rows)`` gets each block of recorded rows.

        ``rows`` is a ``RowBlock`` (orchestrator/support/rows.py: no numpy until asked) of n rows of width values: ``[t, outputs of component 0, ...]``,
        the initial point first, then every ``every``-th communication point (the trace writer's
        decimation), at most ``block`` rows; it is overwritten after ``sink`` returns (copy to keep).
        ``sink=None`` records nothing (tracing off). ``tick(k)`` is called after each call into C.
        ``initialize=False``: the caller already called ``initialize(start_time)``.
        ``check()`` runs after every step: if it raises, the run stops there (between two steps),
        the rows recorded so far go to ``sink`` and the exception propagates.
        ``deliver_interval`` (s of wall time): a partial block goes to ``sink`` when this much time
        passed since the last one, so that a consumer writing to disk never lags far behind.
        ``call_steps``: steps per call into C when delivering on an interval (default ``CALL_STEPS``;
        fewer for a live view, which paces the run in ``tick`` and wants a block per frame).
        """
        if every < 1:
            raise ValueError("every must be >= 1")
        core = self._core
        initial = self.initialize(start_time) if initialize else self._core.outputs()
        h, t0 = float(step), float(start_time)
        if sink is None:
            k = 0
            chunk = max(block, 1) * every
            while k < steps:
                stop = min(steps, k + chunk)
                try:
                    core.run(t0, h, k, stop, None, 1, 0, check)
                finally:
                    self.time = t0 + (k + core.steps_done) * h
                k = stop
                if tick is not None:
                    tick(k)
            return
        width = self.width
        capacity = max(block, 2)
        buffer = float_buffer(capacity, width)
        first = array("d", (start_time,))
        first.extend(value for values in initial for value in values)
        buffer[:width] = first
        row, k = 1, 0
        call_steps = (call_steps or CALL_STEPS) if deliver_interval is not None else steps
        delivered = clock.monotonic()
        while k < steps:
            # as many steps as fill the buffer: rows are recorded after steps k with (k + 1) % every == 0
            stop = min(steps, (k // every + capacity - row) * every, k + call_steps)
            try:
                core.run(t0, h, k, stop, buffer, every, row, check)
            except BaseException:
                self.time = t0 + (k + core.steps_done) * h
                done = row + core.rows_done
                if done:
                    sink(RowBlock(buffer[:done * width], width))
                raise
            row += core.rows_done
            k = stop
            self.time = t0 + k * h
            due = deliver_interval is not None and clock.monotonic() - delivered >= deliver_interval
            if row == capacity or k == steps or (due and row):
                if row:
                    sink(RowBlock(buffer[:row * width], width))
                row = 0
                delivered = clock.monotonic()
            if tick is not None:
                tick(k)

    def close(self) -> None:
        self._core.close()

