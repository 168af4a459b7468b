"""The server's side of a remote vehicle: one FMU instance answering the served-FMU protocol.

``platoon serve`` (orchestrator/cli/serve.py) opens a Zenoh session and hands every query on its key
to ``ServedInstance.handle``, which answers it from an ``FmuComponent``: the very class a local run
steps (``Fmu3Component`` for an FMI 3.0 FMU: orchestrator/components/fmu3.py), so a remote vehicle
computes what a local one would, bit for bit (the inputs and outputs cross the wire as the f64 they are). The protocol and its rules are in bridge/fmu_wire.py; this module keeps
them: one run's token owns the instance, requests execute once and in order.

An instance whose run falls silent (its host killed, a partition) for ``lease`` seconds is freed, so
the server can serve the next run; ``expire`` is called by the serving loop.
"""

from __future__ import annotations

import ctypes
import hmac
import threading
import time
from dataclasses import dataclass, field
from typing import Any, Callable

import zenoh

from bridge import fmu_wire as wire
from fmus.errors import ComponentError
from orchestrator.components.fmu import FmuComponent, UnpackedFmu
from orchestrator.components.fmu3 import fmu_component


@dataclass
class _Held:
    """The instance one run owns: its token, the last request executed and that request's reply."""

    token: bytes
    component: FmuComponent
    seq: int = 0
    reply: bytes = b""
    initialized: bool = False


@dataclass
class ServedInstance:
    """One FMU, instantiated for one run at a time."""

    fmu: UnpackedFmu
    lease: float = 60.0
    clock: Callable[[], float] = time.monotonic
    on_event: Callable[[str], None] = lambda line: None
    _held: _Held | None = None
    _last_request: float = 0.0
    _lock: threading.Lock = field(default_factory=threading.Lock)
    steps: int = 0  # steps executed, for the server's report

    def handle(self, payload: bytes) -> bytes:
        """The reply to one request (never raises: a bad or foreign request is a refusal)."""
        try:
            op, token, seq, body = wire.parse_request(payload)
        except wire.WireError as error:
            return wire.reply_refused(f"malformed request: {error}")
        if op == wire.PING:
            return wire.reply_ok()
        with self._lock:
            try:
                return self._handle(op, token, seq, body)
            except (wire.WireError, ValueError) as error:
                return wire.reply_refused(str(error))
            except ComponentError as error:
                return wire.reply_refused(f"{error.reason} (t = {error.time:.6g} s)")

    def _handle(self, op: int, token: bytes, seq: int, body: bytes) -> bytes:
        held = self._held
        if op == wire.OPEN:
            return self._open(token, seq, body)
        if held is None or not hmac.compare_digest(held.token, token):
            return wire.reply_refused("no instance of this run here (never opened, freed, or another run's)")
        self._last_request = self.clock()
        if seq == held.seq:  # a retry after a lost reply: the same answer, nothing executed again
            return held.reply
        if seq != held.seq + 1:
            return wire.reply_refused(f"request {seq} out of order (the last executed was {held.seq})")
        reply = self._execute(held, op, body)
        held.seq, held.reply = seq, reply
        if op == wire.FREE:
            self._free("freed by its run")
        return reply

    def _open(self, token: bytes, seq: int, body: bytes) -> bytes:
        held = self._held
        if held is not None and not hmac.compare_digest(held.token, token):
            return wire.reply_refused("busy: this server's instance belongs to another run")
        if held is not None:  # the same run asking again (its first reply was lost)
            return held.reply if held.seq == 0 else wire.reply_refused("already opened and in use")
        if seq != 0:
            return wire.reply_refused(f"open numbered {seq}, expected 0")
        request = wire.parse_json(body, "open")
        if not isinstance(request, dict) or not isinstance(request.get("parameters"), dict):
            raise wire.WireError("open: expected {\"name\", \"start\", \"parameters\"}")
        name, start = str(request.get("name") or "remote"), float(request.get("start", 0.0))
        component = fmu_component(name, self.fmu, request["parameters"])
        try:
            component.initialize(start)
        except ComponentError:
            component.close()
            raise
        description = {"fmu": self.fmu.path.name, "guid": self.fmu.guid, "inputs": component.inputs,
                       "outputs": component.outputs, "input_defaults": component.input_defaults}
        self._held = _Held(token, component, 0, wire.reply_ok(wire.json_body(description)))
        self._last_request = self.clock()
        self.steps = 0
        self.on_event(f"opened {name} for a run")
        return self._held.reply

    def _execute(self, held: _Held, op: int, body: bytes) -> bytes:
        component = held.component
        if op == wire.STEP:  # the inputs and outputs stay the f64 bytes they are on the wire (no Python floats)
            time_, step, inputs = wire.parse_step(body)
            component.set_input_bytes(inputs)
            component.step(time_, step)
            self.steps += 1
            return wire.reply_ok(component.output_bytes())
        if op == wire.EXCHANGE:
            if body:
                component.set_input_bytes(memoryview(body))
            return wire.reply_ok(component.output_bytes())
        if op == wire.END_INIT:
            component.end_initialization()
            return wire.reply_ok()
        return wire.reply_ok()  # FREE: the caller frees

    def _free(self, why: str) -> None:
        held, self._held = self._held, None
        if held is not None:
            held.component.close()
            self.on_event(f"{held.component.name} {why} after {self.steps} steps")

    def expire(self) -> None:
        """Free an instance whose run has been silent for ``lease`` seconds."""
        with self._lock:
            if self._held is not None and self.clock() - self._last_request > self.lease:
                self._free(f"freed: its run was silent for {self.lease:g} s")

    def close(self) -> None:
        with self._lock:
            self._free("freed: the server stops")


def _keep_thread_state() -> None:
    """Keep the Python thread state of the (non-Python) thread this is called on until the thread ends.

    A Zenoh thread that calls into Python gets a thread state made for the call and deleted after it
    (``PyGILState_Ensure``/``Release``, pyo3's ``with_gil``); one more ``Ensure`` that is never released
    keeps it, so the next call only takes the GIL (docs/remote.md, "One round trip per step": about a
    quarter less of a server's CPU per request). Called once per thread, from the thread itself."""
    if not getattr(_thread_state_kept, "done", False):
        ctypes.pythonapi.PyGILState_Ensure()
        _thread_state_kept.done = True


_thread_state_kept = threading.local()


def serve(instance: ServedInstance, session: Any, key: str, stop: threading.Event, on_zenoh_thread: bool = False) -> None:
    """Answer queries on ``key`` until ``stop`` is set; the instance is freed on the way out.

    ``on_zenoh_thread``: answer each query on the Zenoh thread that read it, not on zenoh-python's
    callback thread it would be handed to (a thread hand-over and about three context switches less per
    request: 30-40 % less of the server's CPU, docs/remote.md, "One round trip per step"). Only for a process whose Zenoh serves nothing
    else, ``platoon serve`` (its Zenoh on one thread, bridge/session.py): while the answer runs (the FMU's
    step) that Zenoh thread reads and writes nothing else, and it waits for the GIL whenever another of
    the process's threads holds it. Never in a run or in an FMI importer hosting the client FMU."""
    def answer(query: Any) -> None:
        if on_zenoh_thread:
            _keep_thread_state()
        payload = query.payload.to_bytes() if query.payload is not None else b""
        query.reply(query.key_expr, instance.handle(payload))

    handler = zenoh.handlers.Callback(answer, indirect=False) if on_zenoh_thread else answer
    queryable = session.declare_queryable(key, handler)
    try:
        while not stop.wait(min(1.0, instance.lease / 4)):
            instance.expire()
    finally:
        queryable.undeclare()
        instance.close()
