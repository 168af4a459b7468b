"""The master algorithm: initialize, then exchange values and step every component, in fixed steps.

* Jacobi (default): every component steps from t to t + h with inputs taken from outputs at t, then
  all outputs are read. Every connection carries a one-step delay, in both directions of the paper's
  information flow. This is what libcosim's fixed-step algorithm and FMPy's SSP runner do.
* Gauss-Seidel (front to back: target, vehicle 1, ..., vehicle N): each component steps in turn with
  inputs from the newest outputs, so lateral information (flowing backward, front to back) arrives
  without delay: vehicle i sees vehicle i-1 already at t + h. Velocity information (flowing forward)
  still comes from components that have not stepped yet, values at t, one step late.

With coupling "extrapolate" the FMUs take the sender's ``time`` into account, so both orders are
second-order accurate; with "hold" both are first order (docs/coupling.md).
"""

from __future__ import annotations

import math
from operator import itemgetter
from dataclasses import dataclass
from typing import Callable, Sequence

from orchestrator.components.fmu import Component, ComponentError
from fmus.realtime import Pacer
from orchestrator.scenario.scenario import ScheduledInput
from orchestrator.scenario.wiring import Connection

MASTERS = ("jacobi", "gauss-seidel")

Observer = Callable[[float, list[list[float]]], None]


@dataclass
class Route:
    """Where each input of one component comes from."""

    connected: list[tuple[int, int, int]]  # (input index, source component index, output index)
    scheduled: list[tuple[int, ScheduledInput]]


def resolve_routes(
    components: Sequence[Component], connections: Sequence[Connection], schedules: Sequence[ScheduledInput]
) -> list[Route]:
    """The wiring as index arrays per destination; names that do not exist are a ValueError."""
    index = {c.name: i for i, c in enumerate(components)}

    def lookup(name: str, what: object) -> int:
        if name not in index:
            raise ValueError(f"{what}: no component named {name!r}")
        return index[name]

    def position(names: list[str], name: str, what: object) -> int:
        if name not in names:
            raise ValueError(f"{what}: no variable {name!r}")
        return names.index(name)

    routes = [Route([], []) for _ in components]
    for connection in connections:
        source = lookup(connection.source, connection)
        destination = lookup(connection.destination, connection)
        out = position(components[source].outputs, connection.output, connection)
        inp = position(components[destination].inputs, connection.input, connection)
        routes[destination].connected.append((inp, source, out))
    for schedule in schedules:
        destination = lookup(schedule.component, schedule)
        inp = position(components[destination].inputs, schedule.input, schedule)
        routes[destination].scheduled.append((inp, schedule))
    return routes


def check_finite(components: Sequence[Component], outputs: Sequence[Sequence[float]], time: float) -> None:
    """Non-finite initial outputs fail the run, attributed to the first component holding one."""
    bad = [
        f"{component.name}.{name} = {value}"
        for component, values in zip(components, outputs)
        for name, value in zip(component.outputs, values)
        if not math.isfinite(value)
    ]
    if bad:
        first = bad[0].split(".", 1)[0]
        raise ComponentError(first, time, "initial outputs are not finite: " + ", ".join(bad[:6])
                             + (" ..." if len(bad) > 6 else "") + " (is a vehicle placed on its target?)")


Gather = Callable[[list[float]], Sequence[float]]


def _flat_transfers(components: Sequence[Component], routes: Sequence[Route]) -> tuple[list[slice], list[float], list[Gather]]:
    """Where each component's outputs sit in one flat list, the list (outputs first, NaN until
    published, then the constant inputs), and each component's gather of its input vector from it.

    A connected input reads its source's output (the last connection wins, as in a loop over them);
    any other input reads its start value, which nothing ever changes. Scheduled inputs are
    overwritten after the gather.
    """
    slices, offset = [], 0
    for component in components:
        slices.append(slice(offset, offset + len(component.outputs)))
        offset += len(component.outputs)
    flat = [math.nan] * offset
    gathers: list[Gather] = []
    for component, route in zip(components, routes):
        indices = []
        for value in component.input_defaults:
            indices.append(len(flat))
            flat.append(value)
        for inp, source, out in route.connected:
            indices[inp] = slices[source].start + out
        if len(indices) == 1:
            only = indices[0]
            gathers.append(lambda values, only=only: (values[only],))
        else:
            gathers.append(itemgetter(*indices) if indices else (lambda values: ()))
    return slices, flat, gathers


class Master:
    """The Python engine's master loop, over any ``Component``.

    Transfers run from one flat list of every component's outputs followed by the constant inputs
    (unconnected inputs keep their start values): each component's input vector is one
    ``operator.itemgetter`` call over it, a single C-level gather instead of a Python loop per
    connection. The values moved are the same float objects, so results stay bit-identical to the
    native engine's.
    """

    def __init__(
        self,
        components: Sequence[Component],
        connections: Sequence[Connection],
        schedules: Sequence[ScheduledInput] = (),
        algorithm: str = "jacobi",
        pacer: Pacer | None = None,
    ) -> None:
        if algorithm not in MASTERS:
            raise ValueError(f"unknown master {algorithm!r}; expected one of {', '.join(MASTERS)}")
        self.components = list(components)
        self.algorithm = algorithm
        # With a pacer (a live component in the run), outputs that describe t + h are read only once
        # the wall clock has reached t + h; realtime components are the ones whose outputs need it.
        self.pacer = pacer
        self._realtime = [getattr(c, "realtime", False) for c in self.components]
        self.routes = resolve_routes(self.components, connections, schedules)
        self.outputs: list[list[float]] = [[] for _ in self.components]
        self.time = 0.0
        self._slices, self._flat, self._gathers = _flat_transfers(self.components, self.routes)
        self._flat_size = len(self._flat)
        self._transfers = [(c, gather, bool(route.scheduled), component.set_inputs) for c, (gather, route, component)
                           in enumerate(zip(self._gathers, self.routes, self.components))]

    def _publish(self, c: int, values: list[float]) -> None:
        """Make ``values`` component ``c``'s current outputs, for the observer and the transfers."""
        self._flat[self._slices[c]] = values
        if len(self._flat) != self._flat_size:
            self._wrong_output_count([*self.outputs[:c], values])
        self.outputs[c] = values

    def _wrong_output_count(self, outputs: Sequence[Sequence[float]]) -> None:
        """A component returned more or fewer outputs than it declares (say, a live endpoint sending a
        malformed message): fail before any transfer reads a shifted value. The master's outputs stay
        the last complete point."""
        for component, values in zip(self.components, outputs):
            if len(values) != len(component.outputs):
                raise ComponentError(component.name, self.time, f"returned {len(values)} outputs, expected "
                                     f"{len(component.outputs)} ({', '.join(component.outputs)})")
        raise AssertionError("the transfer list changed size")  # pragma: no cover

    def _transfer(self, c: int, t: float) -> None:
        vector = self._gathers[c](self._flat)
        scheduled = self.routes[c].scheduled
        if scheduled:
            vector = list(vector)
            for inp, _ in scheduled:
                vector[inp] = 0.0
            for inp, schedule in scheduled:
                vector[inp] += schedule.value_at(t)
        self.components[c].set_inputs(vector)

    def initialize(self, start_time: float = 0.0) -> list[list[float]]:
        """Enter initialization, propagate initial outputs until they settle, leave initialization."""
        self.time = start_time
        for component in self.components:
            component.initialize(start_time)
        for c, component in enumerate(self.components):
            self._publish(c, component.get_outputs())
        for _ in range(len(self.components) + 2):
            changed = False
            for c, component in enumerate(self.components):
                self._transfer(c, start_time)
                fresh = component.get_outputs()
                changed |= fresh != self.outputs[c]
                self._publish(c, fresh)
            if not changed:
                break
        for component in self.components:
            component.end_initialization()
        for c, component in enumerate(self.components):
            self._publish(c, component.get_outputs())
        check_finite(self.components, self.outputs, self.time)
        return self.outputs

    def step(self, step: float) -> list[list[float]]:
        t = self.time
        components = self.components
        if self.algorithm == "jacobi":
            flat = self._flat
            for c, gather, scheduled, set_inputs in self._transfers:
                if scheduled:
                    self._transfer(c, t)
                else:  # _transfer, inlined for the common case
                    set_inputs(gather(flat))
            for component in components:
                component.step(t, step)
            if self.pacer is not None:
                self.pacer.wait_until(t + step)
            outputs = [component.get_outputs() for component in components]
            for where, values in zip(self._slices, outputs):
                flat[where] = values
            if len(flat) != self._flat_size:
                self._wrong_output_count(outputs)
            self.outputs = outputs
        else:
            pacer = self.pacer
            for c, component in enumerate(components):
                self._transfer(c, t)
                component.step(t, step)
                if pacer is not None and self._realtime[c]:
                    pacer.wait_until(t + step)
                self._publish(c, component.get_outputs())
        return self.outputs

    def run(self, stop_time: float, step: float, observer: Observer, steps: int, start_time: float = 0.0,
            tick: Callable[[int], None] | None = None) -> None:
        """Initialize and run ``steps`` steps of size ``step``, calling ``observer`` at every point."""
        observer(start_time, self.initialize(start_time))
        self.advance(step, observer, steps, start_time, tick)

    def advance(self, step: float, observer: Observer, steps: int, start_time: float = 0.0,
                tick: Callable[[int], None] | None = None) -> None:
        """Run ``steps`` steps of size ``step`` from the initialized state at ``start_time``, calling
        ``observer`` at every point reached and ``tick(k)`` after step k."""
        if self.pacer is not None:
            self.pacer.start(start_time)
        for k in range(steps):
            # t_k = t_0 + k h exactly, and each step spans t_(k+1) - t_k: the FMUs' clocks stay on the
            # grid (no accumulated rounding), as in libcosim's integer-nanosecond clock.
            self.time = start_time + k * step
            following = start_time + (k + 1) * step
            outputs = self.step(following - self.time)
            self.time = following
            observer(self.time, outputs)
            if tick is not None:
                tick(k + 1)

    def close(self) -> None:
        """Close every component, even after one failed to (a live robot's stop must always go out); the first
        failure is raised once all are closed."""
        failure: Exception | None = None
        for component in self.components:
            try:
                component.close()
            except Exception as error:
                failure = failure or error
        if failure is not None:
            raise failure
