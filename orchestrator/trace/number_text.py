"""How every number is written as JSON text, by the writer and the Foxglove channels alike.

Apart from orchestrator/trace/format.py, which every reader imports: orjson (and the uuid and platform modules
it loads) is for writing, and `platoon report` of a stored summary reads no number of the rows.
"""

from __future__ import annotations

try:  # orjson writes floats (Rust, ryu) several times faster than float.__repr__, same values
    import orjson

    def number_texts(values: list[float]) -> list[bytes]:
        """JSON text of each number: shortest text that reads back as exactly the same float."""
        try:
            return orjson.dumps(values)[1:-1].split(b",")
        except TypeError:  # a number type orjson does not take (e.g. numpy scalar): its float value
            return orjson.dumps([float(v) for v in values])[1:-1].split(b",")

except ImportError:  # pragma: no cover - orjson is a dependency; this keeps a bare install working

    def number_texts(values: list[float]) -> list[bytes]:
        """JSON text of each number: shortest text that reads back as exactly the same float."""
        return [float.__repr__(float(v)).encode() for v in values]
