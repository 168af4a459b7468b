"""Run traces in MCAP: the one place to import them from (writer, reader, export, recovery).

The format is in docs/trace-format.md. Writing: ``TraceWriter`` (orchestrator/trace_writer.py) in the
stepping process, or ``TraceWorker`` (orchestrator/trace_worker.py) encoding in a second process.
Reading: ``load(path)`` returns a ``Trace`` with each component's signals as numpy arrays, the config,
metadata, errors and log (orchestrator/trace_reader.py); ``export_csv`` writes one CSV per component;
``recover`` rewrites the complete chunks of an unfinished file (orchestrator/trace_recovery.py).
"""

from __future__ import annotations

from .trace_format import TraceError
from .trace_reader import LogLine, TopicInfo, Trace, decode_log, export_csv, load
from .trace_recovery import Recovery, recover
from .trace_writer import NullTraceWriter, TraceWriter, number_texts

__all__ = [
    "LogLine", "NullTraceWriter", "Recovery", "TopicInfo", "Trace", "TraceError", "TraceWriter", "decode_log",
    "export_csv", "load", "number_texts", "recover",
]
