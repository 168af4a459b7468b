"""Run traces in MCAP: the one place to import them from (writer, reader, export, recovery).

The format is in docs/trace-format.md. The package's modules, each with one job:

Writing
* ``format``: topics, channel kinds, chunk groups and sizes; ``number_text``: how numbers become JSON text
  (orjson: for writing only);
* ``encoding``: each channel as a ``ChannelSpec`` and the components' messages, made once for the
  trace file and the live view (``platoon run --live``, orchestrator/observers/foxglove_view.py);
* ``foxglove``: the derived Foxglove channels (scene, transforms, errors, log); ``viridis`` their colours;
* ``writer``: ``TraceWriter``, encoding rows in the stepping process into chunk groups;
  ``writer_base``: what a run needs of a writer without loading it (errors, the null writer);
* ``native_rows`` (+ ``native_encoder.c``): the per-row messages encoded in C from float64 rows;
* ``mcap_file``: the MCAP file layer (records framed with the ``mcap`` package's public record classes,
  chunk and message indexes, statistics, summary), with the compressor passed in;
* ``chunks``: full chunks compressed on a second thread while the next ones fill;
* ``channel_copy``: the second copy of the schemas and channels, outside the chunks, for recovery;
* ``worker`` + ``serve``: ``TraceWorker``, the same writer in a second process (``serve`` is its
  entry point, ``python -m orchestrator.trace.serve``);
* ``output``: the trace's aside file, put in place only once finalized.

Reading
* ``reader``: ``load(path)`` returns a ``Trace`` with each component's signals as numpy arrays, the
  config, metadata, errors and log; ``export_csv`` writes one CSV per component;
* ``columns`` (+ ``native_decoder.c``): the JSON channels decoded into float64 columns, only the chunks
  and channels asked for;
* ``summary_section``: a finished trace's metadata and its data section's CRC, without its chunks (what
  `platoon report` reads of a trace that stores its run's summary);
* ``recovery``: ``recover`` rewrites the complete chunks of an unfinished or damaged file;
* ``layout``: a Foxglove/Lichtblick layout fitted to one run.

Imports go one way: ``format`` <- ``encoding`` <- ``writer``, ``foxglove``; ``mcap_file``, ``chunks``
<- ``writer`` <- ``worker``/``serve``; ``format`` <- ``reader``, ``recovery``. The names below are loaded
on first use, so that the writer process (``serve``), which imports this package on its way, does not
pay for numpy and the reader.
"""

from __future__ import annotations

from importlib import import_module
from typing import Any

_PUBLIC = {
    "TraceError": "format",
    "number_texts": "number_text",
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
