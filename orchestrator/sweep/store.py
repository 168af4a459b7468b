"""The output folder of a sweep, and what makes it safe to stop at any moment.

```
DIR/results/<id>.json   one per finished run: written to a temporary name, fsynced, renamed (atomic)
DIR/traces/<id>.mcap    the run's trace (written as <id>.mcap.part, renamed when the run finished)
DIR/results.csv         one row per finished run, rebuilt from results/ (atomically) after each run
DIR/results.parquet     the same table, when pyarrow is installed
DIR/.lock               held (flock) by the sweep working on DIR
```

A run counts as done once its result file exists: the rename is the commit. Killed before it, the
run is redone from scratch on restart (its partial trace is removed first); killed after it,
results.csv is rebuilt from the result files on restart. A result made from another resolved config
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

from .plan import Run
from .spec import SweepError

LOCK_WAIT = 10.0  # s to wait for a folder whose previous sweep is just dying (its children go with it)
FIXED_COLUMNS = ("status", "error", "wall_time", "trace")
_VEHICLE = re.compile(r"vehicle(\d+)\.")


def _fsync_dir(folder: Path) -> None:
    fd = os.open(folder, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def write_atomically(path: Path, data: bytes) -> None:
    """Replace ``path`` by ``data`` all at once: readers (and a restart) see the old or the new file, whole."""
    temporary = path.with_name(f".{path.name}.tmp")
    with open(temporary, "wb") as file:
        file.write(data)
        file.flush()
        os.fsync(file.fileno())
    os.replace(temporary, path)
    _fsync_dir(path.parent)


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
        self._records: dict[str, dict[str, Any]] = {}  # id -> the record committed (tables need no re-reading)

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
        record = self._records.get(run.id)
        if record is None:
            try:
                record = json.loads((self.results / f"{run.id}.json").read_text())
            except (OSError, ValueError):
                return None
            self._records[run.id] = record
        return record if record.get("config_hash") == run.config_hash else None

    def place_trace(self, run: Run, partial: Path) -> Path:
        """Move a finished run's trace from its partial name to its own, on disk before the result says so."""
        with open(partial, "rb") as file:
            os.fsync(file.fileno())
        trace = self.trace_path(run)
        os.replace(partial, trace)
        return trace

    def forget(self, run: Run) -> None:
        """Remove what an earlier attempt of ``run`` left: its result first (the commit), then its trace."""
        result = self.results / f"{run.id}.json"
        if result.exists():
            result.unlink()
            _fsync_dir(self.results)
        self._records.pop(run.id, None)
        self.trace_path(run).unlink(missing_ok=True)

    def record(self, run: Run, outcome: dict[str, Any], trace: Path | None) -> dict[str, Any]:
        """Commit ``run``'s outcome (its trace already in place at ``trace``); returns the record."""
        record = {
            "id": run.id, "values": run.values, "status": outcome["status"], "error": " ".join((outcome.get("error") or "").split()),
            "wall_time": outcome.get("wall_time"),
            "trace": str(trace.relative_to(self.root)) if trace is not None else "",
            "metrics": outcome.get("metrics") or {}, "overrides": run.overrides, "config_hash": run.config_hash,
            "config": json.loads(run.config.model_dump_json()) if run.config is not None else None,
        }
        write_atomically(self.results / f"{run.id}.json", json.dumps(record, indent=1).encode())
        self._records[run.id] = record
        return record

    # -- the tables ----------------------------------------------------------------------------------

    def rows(self, runs: list[Run]) -> tuple[list[str], list[dict[str, Any]]]:
        """Columns and rows of the results table: the finished runs of ``runs``, in plan order."""
        records = [record for run in runs if (record := self.result(run)) is not None]
        varied = list(dict.fromkeys(key for run in runs for key in run.values))
        metrics = metric_order(name for record in records for name in record["metrics"])
        columns = ["id", *varied, *FIXED_COLUMNS, *metrics]
        rows = [{"id": r["id"], **r["values"], **{c: r[c] for c in FIXED_COLUMNS}, **r["metrics"]} for r in records]
        return columns, rows

    def write_tables(self, runs: list[Run]) -> int:
        """Rebuild results.csv (and results.parquet with pyarrow) from the result files; returns the rows."""
        columns, rows = self.rows(runs)
        text = io.StringIO()
        writer = csv.DictWriter(text, columns, lineterminator="\n")
        writer.writeheader()
        writer.writerows(rows)
        write_atomically(self.csv, text.getvalue().encode())
        self._write_parquet(columns, rows)
        return len(rows)

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
