"""The run's side of a remote vehicle: a ``Component`` whose FMU instance lives in a ``platoon serve``.

``RemoteComponent`` keeps the component contract (fmus/component.py) by sending each call to its server
over Zenoh (bridge/fmu_wire.py): ``initialize`` opens the instance, ``step`` sends the inputs, the step
and the request for the outputs in one query and returns at once, ``get_outputs`` waits for that
query's reply. The Jacobi master calls ``step`` on every component before it reads any output, so all
remote vehicles of a macro step are asked at once and the step costs one round trip, not one per vehicle;
the servers step in parallel.

Every remote component of a run shares one Zenoh session (``RemoteHost``), opened by the first to start
and closed by the last to close. Waits are bounded: no reply within ``step_timeout`` fails the run with
a ``ComponentError`` naming the vehicle, its server's key and where the server was reached.
"""

from __future__ import annotations

import secrets
import threading
import time
from dataclasses import dataclass, field
from struct import Struct
from typing import Any, Sequence

import zenoh

from bridge import fmu_wire as wire
from bridge.session import open_session, zenoh_config
from fmus.component import ComponentError

CLOSE_TIMEOUT = 0.3  # s to wait for a server to confirm a free: a dead server must not hold the run's exit


@dataclass
class RemoteHost:
    """The Zenoh session every remote component of a run shares (opened on first use)."""

    connect: tuple[str, ...] = ()
    listen: tuple[str, ...] = ()
    zenoh_config: str | None = None
    allow_insecure: bool = False
    _session: Any = None
    _users: int = 0
    _frees: list[Any] = field(default_factory=list)  # the frees sent, answered (or timed out) before closing
    # an importer's worker threads may open (or close) instances of one shared host at once (``shared_host``)
    _lock: threading.Lock = field(default_factory=threading.Lock)

    def acquire(self) -> Any:
        with self._lock:
            if self._session is None:
                config = zenoh_config(self.connect, self.listen, self.zenoh_config, allow_insecure=self.allow_insecure)
                self._session = open_session(config, "the run's remote vehicles")
            self._users += 1
            return self._session

    def release(self, free: Any = None) -> None:
        """One component done (``free``: its free request's reply handle). The last one closes the session,
        once every free is answered or timed out: sent back to back, they take ``CLOSE_TIMEOUT`` together at
        most, however many servers are gone."""
        with self._lock:
            if free is not None:
                self._frees.append(free)
            self._users -= 1
            if self._users <= 0 and self._session is not None:
                for handle in self._frees:
                    first_reply(handle)
                self._frees.clear()
                session, self._session = self._session, None
                session.close()

    def ask(self, key: str, payload: bytes, timeout: float) -> Any:
        """Send one query and return its reply handle at once (``first_reply`` collects the reply)."""
        return self._session.get(key, payload=payload, timeout=timeout,
                                 consolidation=zenoh.ConsolidationMode.NONE)

    def querier(self, key: str, timeout: float) -> Any:
        """A declared querier on ``key``: its ``get`` costs a sixth of the session's (about 10 against 70 us
        of this process's time per call, measured here), which is what lockstep stepping pays per vehicle."""
        return self._session.declare_querier(key, consolidation=zenoh.ConsolidationMode.NONE, timeout=timeout)


_SHARED: dict[tuple[Any, ...], RemoteHost] = {}


def shared_host(connect: tuple[str, ...], listen: tuple[str, ...], zenoh_config: str | None,
                allow_insecure: bool) -> RemoteHost:
    """This process's ``RemoteHost`` for these settings. A process that holds several remote instances
    without a run to share a host for them (an FMI importer running client FMUs, fmus/slaves/RemoteVehicle.py)
    gets one Zenoh session per way of reaching the servers, as a run's remote vehicles share one: two
    sessions could not both listen on one endpoint. Opened by its first user, closed by its last."""
    key = (tuple(connect), tuple(listen), zenoh_config, bool(allow_insecure))
    host = _SHARED.get(key)
    if host is None:
        host = _SHARED[key] = RemoteHost(*key)
    return host


def first_reply(handle: Any) -> bytes | None:
    """The payload of the first reply of ``handle``, or None if the query ended without one."""
    for reply in handle:
        if reply.ok is not None:
            return reply.ok.payload.to_bytes()
        return None
    return None


def _reason(body: bytes) -> str:
    """A server's refusal, as text of at most 300 characters (it comes from the network)."""
    text = body.decode("utf-8", "replace")
    return text if len(text) <= 300 else text[:300] + " ..."


@dataclass
class RemoteComponent:
    """One remote FMU instance behind the ``Component`` interface (module docstring)."""

    name: str
    key: str  # the server's key, <prefix>/fmu/<server>
    where: str  # how the server is reached, for error lines ("tcp/127.0.0.1:7501")
    parameters: dict[str, Any]
    inputs: list[str]
    outputs: list[str]
    input_defaults: list[float]
    host: RemoteHost
    step_timeout: float = 2.0
    connect_timeout: float = 10.0
    realtime: bool = False
    served: dict[str, Any] = field(default_factory=dict)  # what the server said it serves (fmu, guid, ...)
    _token: bytes = b""
    _seq: int = -1
    _time: float = 0.0
    _inputs: Sequence[float] = ()
    _dirty: bool = False
    _pending: Any = None
    _session: Any = None
    _querier: Any = None
    _step_layout: Any = None  # the STEP request's Struct (wire.step_layout), made once the inputs are known
    _output_layout: Any = None  # the outputs' Struct

    def _fail(self, reason: str) -> ComponentError:
        return ComponentError(self.name, self._time, f"{reason} (server {self.key} at {self.where})")

    def _call(self, op: int, body: bytes = b"", timeout: float | None = None) -> Any:
        self._seq += 1
        payload = wire.request(op, self._token, self._seq, body)
        if timeout is None and self._querier is not None:
            return self._querier.get(payload=payload)
        return self.host.ask(self.key, payload, self.step_timeout if timeout is None else timeout)

    def _wait(self, handle: Any, what: str, timeout: float | None = None) -> bytes:
        payload = first_reply(handle)
        if payload is None:
            raise self._fail(f"no reply to {what} within {self.step_timeout if timeout is None else timeout:g} s "
                             "(the server stopped, the network parted, or the server is too slow)")
        try:
            ok, body = wire.parse_reply(payload)
        except wire.WireError as error:
            raise self._fail(f"{what}: {error}") from None
        if not ok:
            raise self._fail(f"{what} refused: {_reason(body)}")
        return body

    def _outputs(self, handle: Any, what: str) -> list[float]:
        """The outputs a reply carries; a reply that is not a whole number of f64 fails the run, naming the server."""
        body = self._wait(handle, what)
        if self._output_layout is not None and len(body) == self._output_layout.size:
            return list(self._output_layout.unpack(body))
        try:
            return wire.unpack_floats(body, "outputs")
        except wire.WireError as error:
            raise self._fail(f"{what}: {error}") from None

    def initialize(self, start_time: float) -> None:
        """Open the instance on the server (instantiate, parameters, initialization mode), retrying while
        the server is not yet reachable, for at most ``connect_timeout`` seconds."""
        self._time = start_time
        self._session = self.host.acquire()
        self._token = secrets.token_bytes(wire.TOKEN_SIZE)
        body = wire.json_body({"name": self.name, "start": start_time, "parameters": self.parameters})
        deadline = time.monotonic() + self.connect_timeout
        while True:
            left = deadline - time.monotonic()
            self._seq = -1
            payload = first_reply(self._call(wire.OPEN, body, max(0.05, min(self.step_timeout, left))))
            if payload is not None or left <= 0.0:
                break
            time.sleep(0.05)
        if payload is None:
            raise self._fail(f"no server answered within {self.connect_timeout:g} s (is `platoon serve` running there?)")
        try:
            ok, reply = wire.parse_reply(payload)
            if not ok:
                raise self._fail(f"open refused: {_reason(reply)}")
            self.served = wire.parse_json(reply, "open reply")
        except wire.WireError as error:
            raise self._fail(str(error)) from None
        if not isinstance(self.served, dict):
            raise self._fail("open reply: not a JSON object")
        self._querier = self.host.querier(self.key, self.step_timeout)
        self._step_layout = wire.step_layout(len(self.inputs))
        self._output_layout = Struct(f"<{len(self.outputs)}d")
        if self.served.get("inputs") != self.inputs or self.served.get("outputs") != self.outputs:
            self._seq, self._token = -1, b""  # not ours to use: the lease frees it
            raise self._fail(f"serves {self.served.get('fmu')} with other variables than this vehicle's FMU")

    def set_inputs(self, values: Sequence[float]) -> None:
        self._inputs, self._dirty = values, True

    def get_outputs(self) -> list[float]:
        if self._pending is not None:
            handle, self._pending = self._pending, None
            return self._outputs(handle, f"step from t = {self._time:.6g} s")
        body = wire.floats(self._inputs) if self._dirty else b""
        self._dirty = False
        return self._outputs(self._call(wire.EXCHANGE, body), "exchange")

    def end_initialization(self) -> None:
        self._wait(self._call(wire.END_INIT), "end of initialization")

    def step(self, time: float, step: float) -> None:
        """Send the step; its reply (the outputs at ``time + step``) is collected by ``get_outputs``."""
        self._time = time
        self._dirty = False
        if self._querier is None or len(self._inputs) != len(self.inputs):
            self._pending = self._call(wire.STEP, wire.step_body(time, step, self._inputs))
            return
        self._seq += 1  # _call's numbering, with the request packed in one Struct call
        self._pending = self._querier.get(payload=self._step_layout.pack(wire.STEP, self._token, self._seq, time,
                                                                          step, *self._inputs))

    def close(self) -> None:
        """Free the instance; the host waits for the reply (a dead server: ``CLOSE_TIMEOUT`` at most, for all of them)."""
        self._pending = None
        if self._session is None:
            return
        free = None
        try:
            if self._token and self._seq >= 0:
                free = self._call(wire.FREE, timeout=CLOSE_TIMEOUT)
        finally:
            if self._querier is not None:
                self._querier.undeclare()
            self._session, self._querier, self._token = None, None, b""
            self.host.release(free)
