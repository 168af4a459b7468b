"""Blocks of flat float64 rows ``[t, outputs...]`` without numpy: what the native engine hands its observers.

A plain `platoon run` of native FMUs steps in C and ships its rows to the trace worker as bytes; numpy
was imported only to hold those rows, and importing it was a quarter of the run's start-up (a run
should reach its first step in 0.2 s: docs/performance.md, "Start-up"). A ``RowBlock`` is a view of the engine's reused buffer
(a ``memoryview`` of C doubles) with the row width; consumers that compute on the rows (the live
view, the running summary, ROS 2 publishing) ask for ``array()``, which imports numpy then and wraps
the same memory without a copy.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    import numpy as np


def float_buffer(rows: int, width: int) -> memoryview:
    """A writable, zeroed flat buffer of ``rows`` x ``width`` C doubles (format "d")."""
    return memoryview(bytearray(8 * rows * width)).cast("d")


class RowBlock:
    """``len(block)`` rows of ``width`` doubles in ``values`` (flat, C order); a view, valid until the
    producer reuses its buffer (copy what you keep: ``tobytes()``, ``array().copy()``, ``row(i)``)."""

    __slots__ = ("values", "width")

    def __init__(self, values: memoryview, width: int) -> None:
        if width < 1 or len(values) % width:
            raise ValueError(f"{len(values)} values are not whole rows of {width}")
        self.values = values
        self.width = width

    @classmethod
    def of(cls, rows: Any) -> "RowBlock":
        """A block viewing a 2-D float64 array's memory (C-contiguous; copied to be so if it is not)."""
        import numpy as np

        array = np.ascontiguousarray(rows, dtype=np.float64)
        if array.ndim != 2:
            raise ValueError(f"rows must be 2-D, not {array.ndim}-D")
        return cls(memoryview(array.reshape(-1)), array.shape[1] or 1)

    @classmethod
    def coerce(cls, rows: Any) -> "RowBlock":
        """``rows`` if it is a block, else a block viewing it (a 2-D float64 array, e.g. a caller's numpy rows)."""
        return rows if isinstance(rows, RowBlock) else cls.of(rows)

    def __len__(self) -> int:
        return len(self.values) // self.width

    def head(self, count: int) -> "RowBlock":
        """The first ``count`` rows (a view)."""
        return RowBlock(self.values[:count * self.width], self.width)

    def row(self, index: int) -> list[float]:
        """Row ``index`` (negative counts from the end) as floats."""
        if index < 0:
            index += len(self)
        return self.values[index * self.width:(index + 1) * self.width].tolist()

    def time(self, index: int) -> float:
        """The time (first value) of row ``index``."""
        if index < 0:
            index += len(self)
        return self.values[index * self.width]

    def tobytes(self) -> bytes:
        return self.values.tobytes()

    def tolist(self) -> list[list[float]]:
        flat, width = self.values.tolist(), self.width
        return [flat[start:start + width] for start in range(0, len(flat), width)]

    def array(self) -> "np.ndarray":
        """The rows as a (rows, width) float64 numpy array sharing this block's memory (numpy imported now)."""
        import numpy as np

        return np.frombuffer(self.values, dtype=np.float64).reshape(-1, self.width)
