"""The served-FMU protocol: one Zenoh key per served instance, one request and one reply per call.

A ``platoon serve`` process holds one FMU instance at a time (a process of its own, so a crashing FMU
takes down its server, never the run) and answers Zenoh queries on ``<prefix>/fmu/<name>``. The run's
side (``bridge.fmu_client``) asks, the server replies; both are here only as bytes, so the bridge knows
Zenoh and these layouts, not FMI.

Request, little-endian: op u8, token 16 bytes (the run's random secret, drawn when it opens the instance),
seq u64 (the request's number: open is 0, every later request the previous one's + 1), then the body:

* ``OPEN``     JSON: {"name", "start", "parameters"}; the server instantiates, sets the parameters,
               enters initialization; reply JSON: {"fmu", "guid", "inputs", "outputs", "input_defaults"}
* ``EXCHANGE`` n f64 inputs (n = 0: none set), then the outputs are read; reply: the outputs, f64 each
* ``END_INIT`` empty; reply empty
* ``STEP``     t f64, h f64, the inputs f64 each; set, step from t by h, read; reply: the outputs
* ``FREE``     empty; the instance is terminated and freed; reply empty
* ``PING``     empty, any token; reply empty (the bare round trip, for the benchmark)

Reply: status u8 (``OK`` or ``REFUSED``) then the body, or a UTF-8 reason when refused.

The rules the server keeps (``ServedInstance`` in orchestrator/components/served.py): only the token
that opened an instance may use or free it (a stranger's request is refused, and tells it nothing);
requests run in order, exactly once: a request numbered as the last one executed gets that reply
again (a retry after a lost reply), any other number than the next is refused, so nothing ever steps
twice or out of order.
"""

from __future__ import annotations

import json
import struct
from struct import Struct
from typing import Any

OPEN, EXCHANGE, END_INIT, STEP, FREE, PING = 1, 2, 3, 4, 5, 6
OPS = {OPEN: "open", EXCHANGE: "exchange", END_INIT: "end-initialization", STEP: "step", FREE: "free", PING: "ping"}
OK, REFUSED = 0, 1
TOKEN_SIZE = 16
MAX_REQUEST = 1 << 20  # bytes: a larger request is refused unread
_HEAD = Struct(f"<B{TOKEN_SIZE}sQ")
HEAD_SIZE = _HEAD.size
_STEP = Struct("<dd")


class WireError(ValueError):
    """A request or reply that does not follow the layout (the text says what is wrong)."""


def fmu_key(prefix: str, name: str) -> str:
    """The key a served instance answers on."""
    return f"{prefix}/fmu/{name}"


def request(op: int, token: bytes, seq: int, body: bytes = b"") -> bytes:
    return _HEAD.pack(op, token, seq) + body


def parse_request(payload: bytes) -> tuple[int, bytes, int, bytes]:
    """(op, token, seq, body) of a request; WireError when it is not one."""
    if len(payload) < HEAD_SIZE or len(payload) > MAX_REQUEST:
        raise WireError(f"a request of {len(payload)} bytes (expected {HEAD_SIZE} to {MAX_REQUEST})")
    op, token, seq = _HEAD.unpack_from(payload)
    if op not in OPS:
        raise WireError(f"unknown operation {op}")
    return op, token, seq, payload[HEAD_SIZE:]


def floats(values: Any) -> bytes:
    return struct.pack(f"<{len(values)}d", *values)


def unpack_floats(body: bytes, what: str) -> list[float]:
    if len(body) % 8:
        raise WireError(f"{what}: {len(body)} bytes is not a whole number of f64 values")
    return list(struct.unpack(f"<{len(body) // 8}d", body))


def step_body(time: float, step: float, inputs: Any) -> bytes:
    return _STEP.pack(time, step) + floats(inputs)


def step_layout(inputs: int) -> Struct:
    """The whole STEP request of ``inputs`` inputs as one Struct: ``pack(STEP, token, seq, t, h, *inputs)``
    gives ``request(STEP, token, seq, step_body(t, h, inputs))`` in one call (a run packs one per vehicle
    and step)."""
    return Struct(f"<B{TOKEN_SIZE}sQdd{inputs}d")


def parse_step(body: bytes) -> tuple[float, float, memoryview]:
    """(t, h, the inputs' f64 bytes as they came): for a server that copies them into its FMU's array."""
    if len(body) < _STEP.size or (len(body) - _STEP.size) % 8:
        raise WireError(f"a step of {len(body)} bytes (t and h, then whole f64 inputs)")
    time, step = _STEP.unpack_from(body)
    return time, step, memoryview(body)[_STEP.size:]


def json_body(value: Any) -> bytes:
    return json.dumps(value).encode()


def parse_json(body: bytes, what: str) -> Any:
    try:
        return json.loads(body.decode())
    except (UnicodeDecodeError, ValueError) as error:
        raise WireError(f"{what}: not JSON ({error})") from None


def reply_ok(body: bytes = b"") -> bytes:
    return bytes((OK,)) + body


def reply_refused(reason: str) -> bytes:
    return bytes((REFUSED,)) + reason.encode()


def parse_reply(payload: bytes) -> tuple[bool, bytes]:
    """(ok, body) of a reply; a refusal's body is its reason."""
    if not payload or payload[0] not in (OK, REFUSED):
        raise WireError("a reply without a status byte")
    return payload[0] == OK, payload[1:]
