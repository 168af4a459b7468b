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
A sweep refused before its first run removes what it made (``undo``): the disk is left as it was found.
"""

from __future__ import annotations

import contextlib
import csv
import fcntl
import io
import json
import os
import re
import sqlite3
import tempfile
import time
from pathlib import Path
from typing import Any, Iterable, Iterator

from orchestrator.support.output import (OutputError, check_not_input, identity, rename_into_place, replacing, sync_file,
                                         write_bytes)

from .plan import Run
from .spec import SweepError

LOCK_WAIT = 10.0  # s to wait for a folder whose previous sweep is just dying (its children go with it)
FIXED_COLUMNS = ("status", "error", "wall_time", "trace")
TABLE_BATCH = 1_000  # rows per SQLite insert and per parquet row group: memory bounded, whatever the sweep's size
_VEHICLE = re.compile(r"vehicle(\d+)\.")


OWN_FILES = ("results.csv", "results.parquet", ".lock")  # the folder's own files beside results/ and traces/
OWN_FOLDERS = ("results", "traces")


def folder_files(root: Path) -> Iterator[Path]:
    """Every file of the sweep folder ``root`` that a command reading the folder reads (or a sweep resuming
    in it): its tables, its lock, and every file in results/ and traces/, whatever its name."""
    root = Path(root)
    for name in OWN_FILES:
        yield root / name
    for folder in OWN_FOLDERS:
        try:
            with os.scandir(root / folder) as entries:
                for entry in entries:
                    yield Path(entry.path)
        except OSError:  # no such folder (a sweep that never ran there): nothing in it to protect
            continue


def check_not_in_folder(target: Path, root: Path, what: str = "--out") -> None:
    """Refuse ``target`` if it is one of the sweep folder ``root``'s files: by name (results/ and traces/
    are the sweep's, whether the file exists yet or not; results.csv, results.parquet, .lock), by hard
    link or by symlink (compared by device and inode: support/output.py), with or without --overwrite.
    A file drawn from a sweep (its map) may go anywhere else, the folder itself included."""
    check_not_input(Path(target), folder_files(root), what)
    own = _own_name(target, root)
    if own is not None:
        raise OutputError(f"{what} {target}: is {own} of the sweep folder {root} (its tables, lock, results/ and "
                          f"traces/ are the sweep's files, which this command reads); choose another path")


def check_inputs_outside(root: Path, inputs: Iterable[Path], what: str = "--out") -> None:
    """Refuse the sweep folder ``root`` when one of the sweep's ``inputs`` (its sweep file, its base config)
    is one of the files the sweep writes there (results.csv, .lock, a result or a trace): by name, hard
    link or symlink. The sweep would write over what it reads."""
    inputs = [Path(given) for given in inputs]
    for given in inputs:
        own = _own_name(given, root)
        if own is not None:
            raise OutputError(f"{what} {root}: its {own} would be {given}, which this command reads; choose another "
                              f"folder")
    wanted = {identity(given): given for given in inputs}
    wanted.pop(None, None)
    for path in folder_files(root):  # streamed: a folder of 10^5 runs is as cheap in memory as an empty one
        given = wanted.get(identity(path))
        if given is not None:
            raise OutputError(f"{what} {root}: its {path.relative_to(root)} would be {given}, which this command "
                              f"reads; choose another folder")


def _own_name(path: Path, root: Path) -> str | None:
    """The name ``path`` has among the sweep folder's own files (``results.csv``, ``results/<id>.json``),
    symlinks followed; None if it is none of them (whether or not the file exists)."""
    real = Path(os.path.realpath(path))
    places = {Path(os.path.realpath(Path(root) / name)): name for name in OWN_FOLDERS}
    files = {Path(os.path.realpath(Path(root) / name)): name for name in OWN_FILES}
    return f"{places[real.parent]}/{real.name}" if real.parent in places else files.get(real)


class StorageError(OSError):
    """A file of the sweep's bookkeeping that could not be written (a full disk, a read-only folder): the
    message is one line naming the file and what failed; the sweep stops with it (exit 1), the runs
    committed before kept."""


@contextlib.contextmanager
def storing(path: Path, doing: str) -> Iterator[None]:
    """Turn any storage failure while ``doing`` something to the sweep file ``path`` into a ``StorageError``:
    an ``OSError`` (which may not name the file: a failed write or fsync does not), an ``OutputError``
    (the output rule's own line), or an SQLite error ("database or disk is full": the table rebuild's
    scratch table is SQLite's, and sqlite3's errors are not OSErrors)."""
    try:
        yield
    except StorageError:
        raise
    except OutputError as error:
        raise StorageError(str(error)) from None
    except OSError as error:
        raise StorageError(f"sweep file {path}: cannot {doing}: {error.strerror or error}") from None
    except sqlite3.Error as error:
        raise StorageError(f"sweep file {path}: cannot {doing}: {error}") from None


def write_atomically(path: Path, data: bytes) -> None:
    """Replace ``path`` by ``data`` all at once, by the output rule (support/output.py): readers (and a
    restart) see the old or the new file, whole."""
    with storing(path, "write it"):  # the runner treats a folder it cannot write as an OSError (one line)
        write_bytes(path, data, what="sweep file")


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
        self._created: list[Path] = []  # what this invocation made (folders, .lock, results.csv): ``undo``

    # -- the lock ------------------------------------------------------------------------------------

    def acquire(self) -> None:
        """Take the folder for this sweep; SweepError if another sweep holds it."""
        deadline = time.monotonic() + LOCK_WAIT
        while True:
            lock = self._open_lock()
            if self._take(lock, deadline):
                break
        self._lock = lock
        try:
            with storing(self.root / ".lock", "write the sweep's pid in it"):  # unbuffered: nothing left to fail on close
                os.ftruncate(lock.fileno(), 0)
                os.pwrite(lock.fileno(), str(os.getpid()).encode(), 0)
            with storing(self.root, "remove the leftovers of a killed sweep"):
                self._remove_leftovers()
        except StorageError:  # e.g. a disk already full: nothing ran, the disk is left as it was found
            self.undo()
            self.release()
            raise

    def _open_lock(self) -> io.TextIOWrapper:
        """The folder's .lock, opened (the folder made first, and what is made noted for ``undo``)."""
        try:
            self._make_folder(self.results)
            self._make_folder(self.traces)
            self._note_new(self.root / ".lock", self.csv)
            return open(self.root / ".lock", "a+")
        except OSError as error:
            self.undo()
            raise SweepError(f"--out {self.root}: cannot write there: {error.strerror or error}") from None

    def _take(self, lock: io.TextIOWrapper, deadline: float) -> bool:
        """Lock ``lock``, waiting until ``deadline`` for a sweep that is just dying; False (closed) if the
        file was meanwhile removed by a sweep refused up front (``undo``): then open it again."""
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
        held = os.fstat(lock.fileno())
        try:
            now = os.stat(self.root / ".lock")
        except OSError:
            now = None
        if now is None or (now.st_dev, now.st_ino) != (held.st_dev, held.st_ino):
            lock.close()
            return False
        return True

    def _make_folder(self, folder: Path) -> None:
        """``mkdir -p folder``, noting each folder it makes (the root's parents included)."""
        missing = []
        while not os.path.lexists(folder):
            missing.append(folder)
            folder = folder.parent
        for made in reversed(missing):
            try:
                made.mkdir()
            except FileExistsError:  # made meanwhile by someone else: not ours to remove
                continue
            self._created.append(made)

    def _note_new(self, *files: Path) -> None:
        self._created += [path for path in files if not os.path.lexists(path)]

    def undo(self) -> None:
        """Remove what this invocation made, for a sweep refused before its first run (the disk estimate, a
        table it cannot write): the disk is left as it was found. Only what it made, and only if nothing
        else came into it meanwhile (a folder is removed only when empty); call it holding the lock."""
        for path in reversed(self._created):
            with contextlib.suppress(OSError):
                path.rmdir() if path.is_dir() and not path.is_symlink() else path.unlink()
        self._created = []

    def release(self) -> None:
        if self._lock is not None:
            with contextlib.suppress(OSError):  # the flock goes with the descriptor, which close() always releases
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
        """Move a finished run's trace from its partial name to its own, on disk before the result says so:
        its data synced, renamed, and traces/ synced (a power cut after the commit keeps the rename too)."""
        trace = self.trace_path(run)
        with storing(trace, "put the run's trace in place"):
            rename_into_place(partial, trace)
        return trace

    def forget(self, run: Run) -> None:
        """Remove what an earlier attempt of ``run`` left: its result first (the commit), then its trace."""
        result = self.results / f"{run.id}.json"
        with storing(result, "remove an earlier attempt's result"):
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

    def _sorted_rows(self, scratch: Path) -> tuple[sqlite3.Connection, set[str], dict[str, set[str]], int, int]:
        """Every result file's row, put in plan order (``index``; records without one last) by a temporary
        SQLite table on disk (``scratch``): memory stays flat however many runs the folder holds. Returns
        the open table, the metric names, each column's value kinds (for the parquet schema), the rows
        and how many of them are not completed."""
        db = sqlite3.connect(scratch)
        db.execute("PRAGMA journal_mode = OFF")  # a scratch table: nothing to recover if we die
        db.execute("PRAGMA synchronous = OFF")
        db.execute("PRAGMA cache_size = -1024")  # KiB of pages held in memory; the rest stays on disk
        # the key is the plan order: rows come out of the B-tree in order, with no sort in memory
        db.execute("CREATE TABLE rows (late INTEGER, position INTEGER, id TEXT, row TEXT, "
                   "PRIMARY KEY (late, position, id)) WITHOUT ROWID")
        metrics: set[str] = set()
        kinds: dict[str, set[str]] = {}
        count = failed = 0
        batch: list[tuple[int, int, str, str]] = []
        with os.scandir(self.results) as entries:
            for entry in entries:
                if not entry.name.endswith(".json") or entry.name.startswith("."):
                    continue
                try:
                    with open(entry.path, "rb") as stream:
                        record = json.loads(stream.read())
                    row = self._row(record)
                except (OSError, ValueError, KeyError, TypeError):
                    continue  # a result file that does not read: its run is redone when the plan reaches it
                metrics.update(record["metrics"])
                for column, value in row.items():
                    kinds.setdefault(column, set()).add(_kind(value))
                count += 1
                failed += record["status"] != "completed"
                index = record.get("index")
                batch.append((index is None, index or 0, record["id"], json.dumps(row)))
                if len(batch) >= TABLE_BATCH:
                    db.executemany("INSERT OR REPLACE INTO rows VALUES (?, ?, ?, ?)", batch)
                    batch.clear()
        db.executemany("INSERT OR REPLACE INTO rows VALUES (?, ?, ?, ?)", batch)
        return db, metrics, kinds, count, failed

    def write_tables(self, varied: list[str], parquet: bool = True) -> tuple[int, int]:
        """Rebuild results.csv (and results.parquet with pyarrow) from the result files; returns the rows
        and how many of them are not completed. Once when a sweep starts and once when it ends (or on
        sweep-plot): O(runs done) in time, streamed (flat in memory), not per run."""
        with storing(self.csv, "rebuild it (its scratch table in the folder)"):
            return self._write_tables(varied, parquet)

    def _write_tables(self, varied: list[str], parquet: bool) -> tuple[int, int]:
        fd, name = tempfile.mkstemp(prefix=".tables.", suffix=".tmp", dir=self.root)  # removed on start if we die
        os.close(fd)
        scratch = Path(name)
        try:
            db, metrics, kinds, count, failed = self._sorted_rows(scratch)
            try:
                columns = ["id", *varied, *FIXED_COLUMNS, *metric_order(metrics)]

                def rows() -> Iterator[dict[str, Any]]:
                    for (text,) in db.execute("SELECT row FROM rows ORDER BY late, position, id"):
                        yield json.loads(text)

                self._write_csv(columns, rows())
                if parquet:
                    self._write_parquet(columns, kinds, rows())
            finally:
                db.close()
        finally:
            scratch.unlink(missing_ok=True)
        return count, failed

    def _write_csv(self, columns: list[str], rows: Iterable[dict[str, Any]]) -> None:
        with replacing(self.csv, "sweep file") as aside, open(aside, "w", newline="") as stream:
            writer = csv.DictWriter(stream, columns, lineterminator="\n")
            writer.writeheader()
            writer.writerows(rows)
        self._header = columns

    def append_row(self, record: dict[str, Any], varied: list[str]) -> None:
        """Add ``record``'s row to results.csv (appended: constant cost per run); the table is rebuilt
        only when the row has a column the header lacks. Not synced: the result file is the commit (synced
        before it is renamed), and the table is rebuilt from the result files when a sweep starts, so a
        row a power cut cuts short is made whole by the next invocation; a reader sees each row once
        written (it is flushed)."""
        header = getattr(self, "_header", None)
        row = self._row(record)
        if header is None or not set(row) <= set(header):
            self.write_tables(varied, parquet=False)
            return
        line = io.StringIO()
        csv.DictWriter(line, header, lineterminator="\n").writerow(row)
        with storing(self.csv, f"append run {record['id']}'s row"), open(self.csv, "a") as table:
            table.write(line.getvalue())

    def _write_parquet(self, columns: list[str], kinds: dict[str, set[str]], rows: Iterable[dict[str, Any]]) -> None:
        """results.parquet, written row group by row group (``TABLE_BATCH`` rows): flat in memory."""
        try:
            import pyarrow
            import pyarrow.parquet
        except ImportError:
            return
        schema = pyarrow.schema([(column, _arrow_type(pyarrow, kinds.get(column, set()))) for column in columns])
        text = {column for column in columns if pyarrow.types.is_string(schema.field(column).type)}

        def batch_of(chunk: list[dict[str, Any]]) -> Any:
            values = {column: [row.get(column) for row in chunk] for column in columns}
            for column in text:  # mixed types (a grid of 1 and "a"): as text
                values[column] = [None if value is None else str(value) for value in values[column]]
            return pyarrow.table(values, schema=schema)

        with storing(self.parquet, "write it"):
            try:
                with replacing(self.parquet, "sweep file") as aside:
                    with pyarrow.parquet.ParquetWriter(str(aside), schema) as writer:
                        chunk: list[dict[str, Any]] = []
                        for row in rows:
                            chunk.append(row)
                            if len(chunk) >= TABLE_BATCH:
                                writer.write_table(batch_of(chunk))
                                chunk.clear()
                        writer.write_table(batch_of(chunk))
            except pyarrow.ArrowException as error:  # an Arrow I/O failure that is not an OSError
                raise OSError(str(error)) from None


def _kind(value: Any) -> str:
    """What a value is, for the column's parquet type: null, bool, int, float or str."""
    if value is None:
        return "null"
    if isinstance(value, bool):
        return "bool"
    if isinstance(value, int):
        return "int"
    if isinstance(value, float):
        return "float"
    return "str"


def _arrow_type(pyarrow: Any, kinds: set[str]) -> Any:
    """The parquet type of a column holding ``kinds`` of values (as pyarrow would infer from the whole column)."""
    kinds = kinds - {"null"}
    if not kinds:
        return pyarrow.null()
    if kinds == {"bool"}:
        return pyarrow.bool_()
    if kinds == {"int"}:
        return pyarrow.int64()
    if kinds <= {"int", "float"}:
        return pyarrow.float64()
    return pyarrow.string()
