"""Run traces in MCAP: the one place to import them from (writer, reader, export, recovery).

The format is in docs/trace-format.md. The package's modules, each with one job:

* ``format``: topics, channel kinds, chunking constants, how numbers become JSON text;
* ``encoding``: each channel as a ``ChannelSpec`` and the components' messages, made once for the
  trace file and the live view (``platoon run --live``, orchestrator/observers/foxglove_view.py);
* ``writer``: ``TraceWriter``, encoding in the stepping process;
* ``worker`` + ``serve``: ``TraceWorker``, the same writer in a second process (``serve`` is its
  entry point, ``python -m orchestrator.trace.serve``);
* ``foxglove``: the derived Foxglove channels (scene, transforms, errors, log) and the layout;
* ``reader``: ``load(path)`` returns a ``Trace`` with each component's signals as numpy arrays, the
  config, metadata, errors and log; ``export_csv`` writes one CSV per component;
* ``recovery``: ``recover`` rewrites the complete chunks of an unfinished file.

Imports go one way: ``format`` <- ``encoding`` <- ``writer``, ``foxglove``; ``writer`` <-
``worker``/``serve``; ``format`` <- ``reader``, ``recovery``. The names below are loaded on first use, so that the writer process
(``serve``), which imports this package on its way, does not pay for numpy and the reader.
"""

from __future__ import annotations

from importlib import import_module
from typing import Any

_PUBLIC = {
    "TraceError": "format",
    "number_texts": "format",
    "LogLine": "reader",
    "TopicInfo": "reader",
    "Trace": "reader",
    "decode_log": "reader",
    "export_csv": "reader",
    "load": "reader",
    "Recovery": "recovery",
    "recover": "recovery",
    "NullTraceWriter": "writer",
    "TraceWriter": "writer",
}

__all__ = sorted(_PUBLIC)


def __getattr__(name: str) -> Any:
    module = _PUBLIC.get(name)
    if module is None:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    value = getattr(import_module(f"{__name__}.{module}"), name)
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(__all__))
