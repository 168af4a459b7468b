"""The run's summary kept in its trace: what `platoon run` computed from the rows it recorded (the per-vehicle
summary, what each link did, where the run left the model), as the trace's ``platoon.summary`` metadata, so
that `platoon report` prints it without reading the rows back or importing numpy (docs/performance.md,
"Start-up": numpy, the reading and the analysis were three quarters of a report).

It is the same computation over the same rows: the run folds each row as the trace records it
(orchestrator/observers/summary.py, validity.py, link_stats.py), the report folds the rows read back, with one
implementation of each quantity. A stored summary is used only while it is what this installation would
compute: the record names the code that computed it (``code_digest``, a digest of ``SOURCES``); a trace
written by other code (an older version, an edited checkout) is summarized from its rows, as before.

Only encoding and decoding here; the trace layer reads and writes the record.
"""

from __future__ import annotations

import json
import zlib
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

from orchestrator.analysis.link_stats import LinkStats
from orchestrator.analysis.summary_fields import VehicleSummary
from orchestrator.analysis.validity import Departure

RECORD = "platoon.summary"  # the metadata record's name
FORMAT = "1"  # the record's own layout
# every source the stored numbers depend on, beside the rows and the config the trace keeps (relative to the
# folder holding the packages: the checkout, or site-packages)
SOURCES = (
    "orchestrator/analysis/metrics.py", "orchestrator/analysis/summary_fields.py",
    "orchestrator/analysis/validity.py", "orchestrator/analysis/link_stats.py",
    "orchestrator/analysis/stored_summary.py", "orchestrator/observers/summary.py",
    "orchestrator/observers/validity.py", "orchestrator/observers/link_stats.py",
    "orchestrator/scenario/scenario.py", "orchestrator/trace/format.py", "fmus/model/paths.py",
)
_ROOT = Path(__file__).resolve().parents[2]


@dataclass(frozen=True)
class StoredSummary:
    """What a run stored: the per-vehicle summary, the links and the departures, as `platoon run` printed them."""

    vehicles: list[VehicleSummary]
    links: list[LinkStats]
    departures: list[Departure]


def code_digest() -> str:
    """A digest of the summary's sources as installed here (a missing one counts as such), against accidental
    change, not forgery: CRC-32 and Adler-32 of the lot (hashlib's import alone would be 2 % of a report)."""
    crc, adler = 0, 1
    for name in SOURCES:
        try:
            data = (_ROOT / name).read_bytes()
        except OSError:
            data = b"missing"
        framed = name.encode() + b"\0" + len(data).to_bytes(8, "little") + data
        crc, adler = zlib.crc32(framed, crc), zlib.adler32(framed, adler)
    return f"{crc:08x}{adler:08x}"


def summary_record(stored: StoredSummary) -> dict[str, str]:
    """The ``platoon.summary`` record (MCAP metadata: strings). Floats as JSON numbers (repr: exact round
    trip); nan and inf as JSON's NaN and Infinity, which ``json.loads`` reads back."""
    def rows(items: list[Any]) -> str:
        return json.dumps([asdict(item) for item in items])

    return {"format": FORMAT, "code": code_digest(), "vehicles": rows(stored.vehicles), "links": rows(stored.links),
            "departures": rows(stored.departures)}


def stored_summary(record: dict[str, str] | None) -> StoredSummary | None:
    """The summary in a ``platoon.summary`` record, or None when there is none, it was computed by other code,
    or it is not one this code wrote (a trace is a file from anywhere: anything amiss means "read the rows")."""
    if not record or record.get("format") != FORMAT or record.get("code") != code_digest():
        return None
    try:
        vehicles = [VehicleSummary(**_typed(item, VehicleSummary)) for item in json.loads(record["vehicles"])]
        links = [LinkStats(**_typed(item, LinkStats)) for item in json.loads(record["links"])]
        departures = [Departure(**_typed(item, Departure)) for item in json.loads(record["departures"])]
    except (KeyError, TypeError, ValueError):
        return None
    return StoredSummary(vehicles, links, departures) if vehicles else None


def _typed(item: Any, kind: type) -> dict[str, Any]:
    """``item``'s fields checked against ``kind``'s annotations (str, int or float; a float may be nan)."""
    if not isinstance(item, dict) or set(item) != set(kind.__dataclass_fields__):
        raise ValueError(f"not a {kind.__name__}")
    for name, field in kind.__dataclass_fields__.items():
        value, wanted = item[name], field.type
        if wanted == "str" and not isinstance(value, str):
            raise ValueError(name)
        if wanted == "int" and (not isinstance(value, int) or isinstance(value, bool)):
            raise ValueError(name)
        if wanted == "float":
            if isinstance(value, bool) or not isinstance(value, (int, float)):
                raise ValueError(name)
            item[name] = float(value)
    return item
