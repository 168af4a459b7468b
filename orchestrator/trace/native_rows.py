"""The trace's per-row messages encoded in C (orchestrator/trace/native_encoder.c), from float64 rows.

A traced run of the native engine spent most of its time encoding the trace in Python (about 16 µs
per component and row: JSON texts, the Foxglove errors, scene and transforms, the MCAP framing;
docs/performance.md). The C encoder writes the same bytes from the engine's float64 blocks (or the
bytes the trace worker received) without a Python object per value: every component's JSON row,
``/platoon/errors``, and at the scene's rate ``/platoon/tf`` and ``/platoon/scene``, framed as MCAP
Message records with their message index entries. The writer (orchestrator/trace/writer.py) keeps
everything else: the chunks (compression, chunk index, the flush every ``FLUSH_INTERVAL``), the
log, live and metadata records, the statistics and the summary.

``encoding.ComponentMessages`` and ``foxglove.FoxgloveChannels`` stay the reference: the Python
engine's rows go through them, and tests/test_trace_native.py holds the two to the same messages.
No numpy here: the trace worker process imports this module.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any, Sequence

from .encoding import ComponentMessages

if TYPE_CHECKING:
    from .foxglove import FoxgloveChannels

try:
    from . import _native  # type: ignore[attr-defined]
except ImportError:  # not built (no C compiler at install time): the Python encoder writes every row
    _native = None

REFUSED_ROW = 1  # a value of the row is not finite
REFUSED_ERRORS = 2  # a /platoon/errors value is not finite


def available() -> bool:
    """True when the C encoder is built."""
    return _native is not None


def native_encoder(messages: ComponentMessages, channels: Sequence[int],
                   foxglove: "FoxgloveChannels | None", groups: dict[int, int] | None = None) -> Any | None:
    """A C encoder of ``messages``' rows on ``channels`` (their ids, in order) and of ``foxglove``'s
    errors, scene and transforms, each channel's messages into its chunk group's records (``groups``:
    channel id -> group; absent: group 0); None when the extension is not built or the run's path is
    one the C encoder cannot measure (then the Python encoder writes the rows)."""
    if _native is None:
        return None
    starts = [start for start, _ in messages.spans]
    components = [(channel, start, end - start, pieces)
                  for channel, (start, end), pieces in zip(channels, messages.spans, messages.pieces)]
    arguments = None
    if foxglove is not None:
        arguments = foxglove.native_arguments(starts)
        if arguments is None:
            return None
    width = 1 + sum(len(outputs) for _, outputs in messages.components)
    group_of = [0] * (1 + max(groups, default=0)) if groups else None
    for channel, group in (groups or {}).items():
        group_of[channel] = group  # type: ignore[index]
    return _native.Encoder(width, components, arguments, group_of)


def row_values(data: Any, width: int, row: int) -> list[float]:
    """Row ``row`` of float64 ``data`` (an array or raw bytes) as floats (for an error message)."""
    return memoryview(data).cast("B").cast("d")[row * width:(row + 1) * width].tolist()


def rows_of(data: Any, width: int) -> list[list[float]]:
    """Float64 ``data`` (an array or raw bytes) as rows of ``width`` floats (the Python encoder's input)."""
    flat = memoryview(data).cast("B").cast("d").tolist()
    return [flat[start:start + width] for start in range(0, len(flat), width)]


def first_non_finite(data: Any, width: int) -> int | None:
    """The first row of flat float64 ``data`` (a buffer: ``RowBlock.values``, raw bytes) holding nan or
    inf, or None; in C, else with numpy (imported only then: a plain run never needs it)."""
    if _native is not None:
        return _native.first_non_finite(data, width)
    import numpy as np

    finite = np.isfinite(np.frombuffer(data, dtype=np.float64).reshape(-1, width)).all(axis=1)
    return None if finite.all() else int(np.argmin(finite))
