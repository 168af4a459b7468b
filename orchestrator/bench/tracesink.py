"""What tracing every step costs the native engine in the benchmarks (engines native-traced and
native-offload): the trace's JSON encoding, written to a zstd-chunked MCAP file.

This is the benchmark's stand-in for the trace writer (orchestrator/trace.py), kept as it was measured
in docs/performance.md while the trace writer's own block encoding is being reworked elsewhere.
"""

from __future__ import annotations

import json
from pathlib import Path


class JsonMcapSink:
    """What a trace costs: one JSON message per component and point (the trace's template and float
    repr, orchestrator/trace.py), written to an MCAP file with zstd chunks of 1 MiB."""

    def __init__(self, path: Path, components: list[tuple[str, list[str]]]) -> None:
        from mcap.writer import CompressionType, Writer

        self.path = path
        self._file = open(path, "wb")
        self._writer = Writer(self._file, compression=CompressionType.ZSTD, chunk_size=1 << 20)
        self._writer.start(profile="", library="platoon-cosim bench")
        self._channels, self._templates, self._slices = [], [], []
        offset = 0
        for name, outputs in components:
            keys = ["t", *outputs]
            schema = self._writer.register_schema(name=f"platoon.{name}", encoding="jsonschema", data=json.dumps(
                {"type": "object", "properties": {k: {"type": "number"} for k in keys}}).encode())
            self._channels.append(self._writer.register_channel(topic=f"/platoon/{name}", message_encoding="json",
                                                                schema_id=schema))
            self._templates.append("{" + ",".join(json.dumps(k).replace("%", "%%") + ":%s" for k in keys) + "}")
            self._slices.append((1 + offset, 1 + offset + len(outputs)))
            offset += len(outputs)
        self.messages = 0
        self._sequence = 0

    def __call__(self, rows) -> None:
        write = self._writer.add_message
        text = float.__repr__
        parts = list(zip(self._channels, self._templates, self._slices))
        for row in rows.tolist():
            t = row[0]
            stamp = int(round(t * 1e9))
            head = text(t)
            for channel, template, (a, b) in parts:
                data = (template % (head, *map(text, row[a:b]))).encode()
                write(channel_id=channel, log_time=stamp, publish_time=stamp, sequence=self._sequence, data=data)
            self._sequence += 1
        self.messages += len(rows) * len(parts)

    def finish(self) -> None:
        self._writer.finish()
        self._file.close()
