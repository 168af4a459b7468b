"""Run traces in MCAP: one JSON channel per component, metadata, and a reader into numpy.

Format (docs/trace-format.md): channel ``/platoon/<component>`` (``target``, ``vehicle1`` ...), JSON
messages with a JSON Schema, one message per recorded communication point holding ``t`` and every
output of the component by its FMU variable name; log_time and publish_time are the simulation time
in nanoseconds. Metadata records ``platoon.config``, ``platoon.fmus``, ``platoon.tool`` and
``platoon.run`` (status, error, engine). Files are chunked, zstd-compressed and indexed.

Rows are buffered and encoded in blocks, so a run's hot loop only appends floats to a list.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Sequence

import numpy as np
from mcap.reader import make_reader
from mcap.writer import CompressionType, Writer

CHANNEL_PREFIX = "/platoon/"
SCHEMA_ENCODING = "jsonschema"
MESSAGE_ENCODING = "json"


def channel_name(component: str) -> str:
    return CHANNEL_PREFIX + component


def _schema(component: str, outputs: Sequence[str], descriptions: dict[str, str]) -> bytes:
    properties = {"t": {"type": "number", "description": "simulation time [s]"}}
    for name in outputs:
        properties[name] = {"type": "number", "description": descriptions.get(name, name)}
    return json.dumps(
        {
            "$schema": "https://json-schema.org/draft/2020-12/schema",
            "title": f"platoon.{component}",
            "type": "object",
            "properties": properties,
            "required": ["t", *outputs],
            "additionalProperties": False,
        }
    ).encode()


class TraceWriter:
    """Writes a run's trace; ``record`` is cheap, ``flush`` encodes buffered rows into the file."""

    def __init__(
        self,
        path: Path,
        components: Sequence[tuple[str, Sequence[str]]],
        descriptions: dict[str, dict[str, str]] | None = None,
        every: int = 1,
        block: int = 500,
    ) -> None:
        self.path = Path(path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._file = open(self.path, "wb")
        self._writer = Writer(self._file, compression=CompressionType.ZSTD, chunk_size=1 << 20)
        self._writer.start(profile="", library="platoon-cosim")
        self.components = [(name, list(outputs)) for name, outputs in components]
        self._channels = []
        for name, outputs in self.components:
            schema_id = self._writer.register_schema(
                name=f"platoon.{name}",
                encoding=SCHEMA_ENCODING,
                data=_schema(name, outputs, (descriptions or {}).get(name, {})),
            )
            self._channels.append(
                self._writer.register_channel(topic=channel_name(name), message_encoding=MESSAGE_ENCODING, schema_id=schema_id)
            )
        self._keys = [["t", *outputs] for _, outputs in self.components]
        self.every = every
        self.block = block
        self._count = 0
        self._rows: list[tuple[float, list[list[float]]]] = []
        self.recorded = 0
        self._closed = False

    def record(self, time: float, outputs: Sequence[Sequence[float]]) -> None:
        """Keep the outputs at ``time`` (every ``every``-th call) for the next flush."""
        if self._count % self.every == 0:
            self._rows.append((time, [list(values) for values in outputs]))
            if len(self._rows) >= self.block:
                self.flush()
        self._count += 1

    def flush(self) -> None:
        write = self._writer.add_message
        for time, outputs in self._rows:
            stamp = int(round(time * 1e9))
            for channel, keys, values in zip(self._channels, self._keys, outputs):
                message = dict(zip(keys, [time, *values]))
                write(channel_id=channel, log_time=stamp, publish_time=stamp, sequence=self.recorded,
                      data=json.dumps(message, allow_nan=False).encode())
            self.recorded += 1
        self._rows.clear()

    def metadata(self, name: str, values: dict[str, Any]) -> None:
        self._writer.add_metadata(name, {k: v if isinstance(v, str) else json.dumps(v) for k, v in values.items()})

    def close(self) -> None:
        if self._closed:
            return
        self.flush()
        self._writer.finish()
        self._file.close()
        self._closed = True


@dataclass
class Trace:
    """A trace read back: per component, a dict of numpy arrays keyed by ``t`` and output names."""

    path: Path
    channels: dict[str, dict[str, np.ndarray]]
    metadata: dict[str, dict[str, str]] = field(default_factory=dict)

    @property
    def config(self) -> dict[str, Any] | None:
        record = self.metadata.get("platoon.config")
        return json.loads(record["resolved"]) if record and "resolved" in record else None

    @property
    def run(self) -> dict[str, str]:
        return self.metadata.get("platoon.run", {})

    def component(self, name: str) -> dict[str, np.ndarray]:
        return self.channels[name]

    def vehicles(self) -> list[str]:
        names = [n for n in self.channels if n.startswith("vehicle")]
        return sorted(names, key=lambda n: int(n[len("vehicle"):]))


def load(path: str | Path) -> Trace:
    """Read a trace (CRCs checked) into numpy arrays, with its metadata."""
    path = Path(path)
    rows: dict[str, list[list[float]]] = {}
    keys: dict[str, list[str]] = {}
    metadata: dict[str, dict[str, str]] = {}
    with open(path, "rb") as stream:
        reader = make_reader(stream, validate_crcs=True)
        for _, channel, message in reader.iter_messages(log_time_order=True):
            name = channel.topic[len(CHANNEL_PREFIX):] if channel.topic.startswith(CHANNEL_PREFIX) else channel.topic
            record = json.loads(message.data)
            if name not in keys:
                keys[name] = list(record)
                rows[name] = []
            rows[name].append([record[k] for k in keys[name]])
        for item in reader.iter_metadata():
            metadata[item.name] = dict(item.metadata)
    channels = {
        name: {key: np.asarray(column, dtype=float) for key, column in zip(keys[name], zip(*rows[name]))}
        for name in rows
    }
    return Trace(path, channels, metadata)


