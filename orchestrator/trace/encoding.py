"""The trace's channels and messages, once, for every sink: the MCAP file and the live view.

A channel is a ``ChannelSpec`` (topic, schema, encodings, metadata); the MCAP writer registers it
with ``register_mcap`` and the live view (orchestrator/observers/foxglove_view.py) advertises the very same spec on
its Foxglove WebSocket server. A message is bytes made here (the components' JSON rows:
``ComponentMessages``; a live link's raw messages: ``LiveStream``) or in ``foxglove.FoxgloveChannels``
(errors, scene, transforms, log): both sinks send the same bytes, so a live viewer and a trace show
the same data under the same schemas.

No numpy, no config: the trace worker process imports this module and should start fast.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from typing import Any, Sequence

from .format import CHANNEL_PREFIX, KIND_KEY, MESSAGE_ENCODING, SCHEMA_ENCODING, channel_name
from .number_text import number_texts


@dataclass(frozen=True)
class ChannelSpec:
    """One channel of a run, as every sink declares it."""

    topic: str
    schema_name: str
    schema_encoding: str
    schema: bytes
    message_encoding: str
    metadata: dict[str, str] = field(default_factory=dict)


def register_mcap(writer: Any, spec: ChannelSpec) -> int:
    """Register ``spec``'s schema and channel on an ``mcap.writer.Writer``; returns the channel id."""
    schema_id = writer.register_schema(name=spec.schema_name, encoding=spec.schema_encoding, data=spec.schema)
    return writer.register_channel(topic=spec.topic, message_encoding=spec.message_encoding, schema_id=schema_id,
                                   metadata=spec.metadata)


def numbers_schema(title: str, keys: Sequence[str], descriptions: dict[str, str]) -> bytes:
    """JSON Schema of an object of numbers: ``t`` (simulation time) and ``keys``."""
    properties = {"t": {"type": "number", "description": "simulation time [s]"}}
    for name in keys:
        properties[name] = {"type": "number", "description": descriptions.get(name, name)}
    return json.dumps(
        {
            "$schema": "https://json-schema.org/draft/2020-12/schema",
            "title": title,
            "type": "object",
            "properties": properties,
            "required": ["t", *keys],
            "additionalProperties": False,
        }
    ).encode()


def json_pieces(keys: Sequence[str]) -> list[bytes]:
    """The JSON object of ``keys`` to numbers, cut where the numbers go: ``{"k0":``, ``,"k1":``, ..., ``}``."""
    return [("{" if i == 0 else ",").encode() + json.dumps(key).encode() + b":" for i, key in enumerate(keys)] + [b"}"]


def template_of(pieces: Sequence[bytes]) -> bytes:
    """The %-format of ``pieces`` (as ``json_pieces`` cuts them): filled with the numbers' texts, the JSON."""
    return b"%s".join(piece.replace(b"%", b"%%") for piece in pieces)


def json_template(keys: Sequence[str]) -> bytes:
    """A %-format that, filled with the values' JSON texts, is the JSON object of ``keys`` to values."""
    return template_of(json_pieces(keys))


def component_spec(name: str, outputs: Sequence[str], descriptions: dict[str, str]) -> ChannelSpec:
    """``/platoon/<component>``: ``t`` and every output, JSON (docs/trace-format.md)."""
    return ChannelSpec(channel_name(name), f"platoon.{name}", SCHEMA_ENCODING,
                       numbers_schema(f"platoon.{name}", outputs, descriptions), MESSAGE_ENCODING,
                       {KIND_KEY: "component"})


class ComponentMessages:
    """The component channels of a run and their messages, from flat rows ``[t, outputs of component 0, ...]``."""

    def __init__(self, components: Sequence[tuple[str, Sequence[str]]],
                 descriptions: dict[str, dict[str, str]] | None = None) -> None:
        self.components = [(name, list(outputs)) for name, outputs in components]
        self.specs = [component_spec(name, outputs, (descriptions or {}).get(name, {})) for name, outputs in self.components]
        # the same JSON cut where the numbers go (orchestrator/trace/native_encoder.c fills the pieces)
        self.pieces = [json_pieces(["t", *outputs]) for _, outputs in self.components]
        self.templates = [template_of(pieces) for pieces in self.pieces]
        self.spans: list[tuple[int, int]] = []
        start = 1
        for _, outputs in self.components:  # where each component's values sit in a row's flat list
            self.spans.append((start, start + len(outputs)))
            start += len(outputs)

    def encode(self, row: Sequence[float]) -> list[bytes]:
        """Each component's JSON message at one row (all values finite)."""
        texts = number_texts(row)  # one conversion per row: the costly part of JSON
        first = texts[0]
        return [template % (first, *texts[start:end]) for template, (start, end) in zip(self.templates, self.spans)]

    def outputs(self, row: Sequence[float]) -> list[Sequence[float]]:
        """A flat row split into each component's outputs (what ``FoxgloveChannels`` takes)."""
        return [row[start:end] for start, end in self.spans]


class LiveStream:
    """A live link's raw messages (e.g. ``/platoon/vehicle3/pose``): JSON numbers, ``t`` first, then ``keys``."""

    def __init__(self, stream: str, keys: Sequence[str]) -> None:
        topic = channel_name(stream)
        name = topic[len(CHANNEL_PREFIX):]
        self.keys = list(keys)
        self.spec = ChannelSpec(topic, f"platoon.{name.replace('/', '.')}", SCHEMA_ENCODING,
                                numbers_schema(f"platoon.{name}", self.keys, {}), MESSAGE_ENCODING, {KIND_KEY: "live"})
        self.template = json_template(["t", *self.keys])

    def encode(self, time: float, values: Sequence[float]) -> bytes:
        return self.template % tuple(number_texts([time, *values]))
