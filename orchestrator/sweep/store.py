"""The output folder of a sweep, and what makes it safe to stop at any moment.

```
DIR/results/<id>.json   one per finished run: written to a temporary name, fsynced, renamed (atomic)
DIR/traces/<id>.mcap    the run's trace (written as <id>.mcap.part, renamed when the run finished)
DIR/results.csv         one row per finished run: appended as each run is committed, rebuilt (in plan
                        order, atomically) from results/ once when the sweep starts and once when it ends
DIR/results.parquet     the same table, when pyarrow is installed: built when the sweep ends
DIR/.lock               held (flock) by the sweep working on DIR
```

A run counts as done once its result file exists: the rename is the commit. Killed before it, the
run is redone from scratch on restart (its partial trace is removed first); killed after it,
results.csv is rebuilt from the result files on restart. Bookkeeping per run is constant: one result
file, one appended row (the table is rewritten only when a run brings a column no row had yet, e.g.
a larger platoon.count's vehicle metrics). A result made from another resolved config
(the base file was edited) is not this run's, and the run is redone. The lock keeps a second sweep
off the folder while one works in it; the kernel releases it when the sweep dies, even by SIGKILL.
"""

from __future__ import annotations

import csv
import fcntl
import io
import json
import os
import re
import time
from pathlib import Path
from typing import Any, Iterable

from orchestrator.support.output import OutputError, sync_file, write_bytes

from .plan import Run
from .spec import SweepError

LOCK_WAIT = 10.0  # s to wait for a folder whose previous sweep is just dying (its children go with it)
FIXED_COLUMNS = ("status", "error", "wall_time", "trace")
_VEHICLE = re.compile(r"vehicle(\d+)\.")


def write_atomically(path: Path, data: bytes) -> None:
    """Replace ``path`` by ``data`` all at once, by the output rule (support/output.py): readers (and a
    restart) see the old or the new file, whole."""
    try:
        write_bytes(path, data, what="sweep file")
    except OutputError as error:  # the runner treats a folder it cannot write as an OSError (one line)
        raise OSError(str(error)) from None


def metric_order(names: Iterable[str]) -> list[str]:
    """Metric columns: vehicle1.* to vehicleN.* by vehicle number, then last.*, fields in report order."""
    names = list(dict.fromkeys(names))
    fields = list(dict.fromkeys(name.split(".", 1)[1] for name in names))

    def key(name: str) -> tuple[int, int, int]:
        match = _VEHICLE.match(name)
        field = fields.index(name.split(".", 1)[1])
        return (0, int(match.group(1)), field) if match else (1, 0, field)

    return sorted(names, key=key)


class OutputFolder:
    def __init__(self, root: Path) -> None:
        self.root = Path(root)
        self.results = self.root / "results"
        self.traces = self.root / "traces"
        self.csv = self.root / "results.csv"
        self.parquet = self.root / "results.parquet"
        self._lock: io.TextIOWrapper | None = None
        self._header: list[str] | None = None  # results.csv's columns as last written

    # -- the lock ------------------------------------------------------------------------------------

    def acquire(self) -> None:
        """Take the folder for this sweep; SweepError if another sweep holds it."""
        try:
            self.results.mkdir(parents=True, exist_ok=True)
            self.traces.mkdir(parents=True, exist_ok=True)
            lock = open(self.root / ".lock", "a+")
        except OSError as error:
            raise SweepError(f"--out {self.root}: cannot write there: {error.strerror or error}") from None
        deadline = time.monotonic() + LOCK_WAIT
        while True:
            try:
                fcntl.flock(lock, fcntl.LOCK_EX | fcntl.LOCK_NB)
                break
            except BlockingIOError:
                if time.monotonic() > deadline:
                    lock.seek(0)
                    holder = lock.read().strip() or "?"
                    lock.close()
                    raise SweepError(f"--out {self.root}: another platoon sweep works in this folder (pid {holder})") from None
                time.sleep(0.1)
        lock.seek(0)
        lock.truncate()
        lock.write(str(os.getpid()))
        lock.flush()
        self._lock = lock
        self._remove_leftovers()

    def release(self) -> None:
        if self._lock is not None:
            self._lock.close()  # closing the file releases the flock
            self._lock = None

    def _remove_leftovers(self) -> None:
        """Partial traces and temporary files of runs a killed sweep had under way (redone now)."""
        # *.partial: the aside file run_scenario writes a trace to until it is finalized (trace/output.py)
        for leftover in [*self.traces.glob("*.part"), *self.traces.glob("*.partial"), *self.results.glob(".*.tmp"),
                         *self.root.glob(".*.tmp")]:
            leftover.unlink(missing_ok=True)

    # -- runs ----------------------------------------------------------------------------------------

    def trace_path(self, run: Run) -> Path:
        return self.traces / f"{run.id}.mcap"

    def partial_trace_path(self, run: Run) -> Path:
        return self.traces / f"{run.id}.mcap.part"

    def result(self, run: Run) -> dict[str, Any] | None:
        """The recorded result of ``run``, if it finished with the config it has now."""
        try:  # read when asked, never cached: memory stays flat in the number of runs
            record = json.loads((self.results / f"{run.id}.json").read_text())
        except (OSError, ValueError):
            return None
        return record if record.get("config_hash") == run.config_hash else None

    def place_trace(self, run: Run, partial: Path) -> Path:
        """Move a finished run's trace from its partial name to its own, on disk before the result says so."""
        sync_file(partial)
        trace = self.trace_path(run)
        os.replace(partial, trace)
        return trace

    def forget(self, run: Run) -> None:
        """Remove what an earlier attempt of ``run`` left: its result first (the commit), then its trace."""
        result = self.results / f"{run.id}.json"
        if result.exists():
            result.unlink()
            sync_file(self.results)  # the removal is on disk before the run is redone
        self.trace_path(run).unlink(missing_ok=True)

    def record(self, run: Run, outcome: dict[str, Any], trace: Path | None, index: int | None = None) -> dict[str, Any]:
        """Commit ``run``'s outcome (its trace already in place at ``trace``); returns the record.
        ``index``: the run's place in the plan (the tables' row order)."""
        record = {
            "id": run.id, "index": index, "values": run.values, "status": outcome["status"], "error": " ".join((outcome.get("error") or "").split()),
            "wall_time": outcome.get("wall_time"),
            "trace": str(trace.relative_to(self.root)) if trace is not None else "",
            "metrics": outcome.get("metrics") or {}, "overrides": run.overrides, "config_hash": run.config_hash,
            "config": json.loads(run.config.model_dump_json()) if run.config is not None else None,
        }
        write_atomically(self.results / f"{run.id}.json", json.dumps(record, indent=1).encode())
        return record

    # -- the tables ----------------------------------------------------------------------------------

    def _row(self, record: dict[str, Any]) -> dict[str, Any]:
        return {"id": record["id"], **record["values"], **{c: record[c] for c in FIXED_COLUMNS}, **record["metrics"]}

    def _columns(self, varied: list[str], records: Iterable[dict[str, Any]]) -> list[str]:
        metrics = metric_order(name for record in records for name in record["metrics"])
        return ["id", *varied, *FIXED_COLUMNS, *metrics]

    def _stored_records(self) -> list[dict[str, Any]]:
        """Every result file of the folder, in plan order (``index``; records without one last)."""
        records = []
        for path in self.results.glob("*.json"):
            try:
                records.append(json.loads(path.read_text()))
            except (OSError, ValueError):
                continue  # a result file that does not read: its run is redone when the plan reaches it
        return sorted(records, key=lambda r: (r.get("index") is None, r.get("index") or 0, r["id"]))

    def write_tables(self, varied: list[str], parquet: bool = True) -> tuple[int, int]:
        """Rebuild results.csv (and results.parquet with pyarrow) from the result files; returns the rows
        and how many of them are not completed.
        Once when a sweep starts and once when it ends (or on sweep-plot): O(runs done), not per run."""
        records = self._stored_records()
        columns = self._columns(varied, records)
        text = io.StringIO()
        writer = csv.DictWriter(text, columns, lineterminator="\n")
        writer.writeheader()
        writer.writerows(self._row(r) for r in records)
        write_atomically(self.csv, text.getvalue().encode())
        self._header = columns
        if parquet:
            self._write_parquet(columns, [self._row(r) for r in records])
        return len(records), sum(r["status"] != "completed" for r in records)

    def append_row(self, record: dict[str, Any], varied: list[str]) -> None:
        """Add ``record``'s row to results.csv (appended and synced: constant cost per run); the table is
        rebuilt only when the row has a column the header lacks."""
        header = getattr(self, "_header", None)
        row = self._row(record)
        if header is None or not set(row) <= set(header):
            self.write_tables(varied, parquet=False)
            return
        line = io.StringIO()
        csv.DictWriter(line, header, lineterminator="\n").writerow(row)
        with open(self.csv, "a") as table:
            table.write(line.getvalue())
            table.flush()
            os.fsync(table.fileno())

    def _write_parquet(self, columns: list[str], rows: list[dict[str, Any]]) -> None:
        try:
            import pyarrow
            import pyarrow.parquet
        except ImportError:
            return
        def array(values: list[Any]) -> Any:
            try:
                return pyarrow.array(values)
            except (pyarrow.ArrowInvalid, pyarrow.ArrowTypeError):  # mixed types (a grid of 1 and "a"): as text
                return pyarrow.array([None if value is None else str(value) for value in values])

        table = pyarrow.table({column: array([row.get(column) for row in rows]) for column in columns})
        sink = pyarrow.BufferOutputStream()
        pyarrow.parquet.write_table(table, sink)
        write_atomically(self.parquet, sink.getvalue().to_pybytes())
