"""Extracted FMUs kept between runs, in a per-user cache, instead of unzipping every FMU in every run.

A run used to extract each FMU into a fresh scratch folder, read its model description from the zip
and check it against the FMI schema, and delete the folder at the end: ~0.05 s of every run's start-up
(docs/performance.md, "Whole runs"). Now each FMU file is extracted once into
``~/.cache/platoon-cosim/fmus/fmu-<stem>-<sha256 of the file, 128 bits>/`` (``$XDG_CACHE_HOME`` is honoured;
``PLATOON_FMU_CACHE`` names another folder, or ``off``), and later runs use that folder.

What keeps it safe:

* **Keyed by content**: the name holds the SHA-256 of the FMU file's bytes, so a rebuilt FMU (same
  path, same GUID or not) gets its own entry, and two FMU kinds of the same name in different folders
  never share one.
* **Checked at every use**: every file the FMU's zip holds must be in the entry with the size and
  CRC-32 the zip's directory records (a few hundred kB read, ~1 ms). A damaged entry (a file
  truncated, edited or deleted) is replaced by a fresh extraction; if another run is using it at that
  moment, this run extracts privately instead (orchestrator/support/scratch.py), as before the cache.
* **Made aside, published atomically**: an entry is extracted into a locked scratch folder inside the
  cache, its model description is checked against the FMI schema there, and only then is the folder
  renamed to its key. A run killed meanwhile leaves a scratch folder whose lock is free, which the next
  run that makes an entry sweeps (orchestrator/support/scratch.py). Two runs making the same entry at once both
  extract; the first rename wins, the second run drops its copy and uses the winner's.
* **Held while in use**: a run holds a shared ``flock`` on the entry's lock file until its FMUs are
  closed; an entry is replaced or evicted only under an exclusive lock, after a rename away from its
  key, so no run ever sees its folder change under it (the kernel drops a killed run's lock).
* **Bounded**: at most ``KEEP`` entries; when a new one is made, the least recently used beyond that
  are removed unless in use.
* **Private**: the cache folder is made for the user alone; one that others can write into is not
  used (it could hold a binary we never unzipped: a CRC is no defence against a forger).

The entry also keeps what a run reads of the model description (``description.json``: the GUID, the
model identifier, each variable's name, value reference, type, causality, variability, initial, start,
description and unit, as FMPy parsed them when the entry was made, with a CRC-32 of its own), so a
run of the native engine needs no FMPy at all (``Description``).

Files the FMU writes into its folder while running (e.g. ``__pycache__`` of a Python FMU's scripts,
which now survive between runs) are not in the zip, and so are neither checked nor in the way.
"""

from __future__ import annotations

import fcntl
import hashlib
import io
import json
import os
import shutil
import time
import zipfile
import zlib
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from orchestrator.support.scratch import LOCK_NAME, PREFIX, ScratchDir, sweep

CACHE_ENV = "PLATOON_FMU_CACHE"
KEEP = 8  # entries kept (the project's FMUs are ~0.3 MB zipped, ~1 MB extracted)
ENTRY_PREFIX = "fmu-"
FILES = "fmu"  # the FMU's own files, inside the entry (beside the lock file)
DESCRIPTION = "description.json"
_VARIABLE_FIELDS = ("name", "valueReference", "type", "causality", "variability", "initial", "start", "description",
                    "unit")
_ATTEMPTS = 4  # an entry vanishing (replaced, evicted) between looking and locking is retried


@dataclass(frozen=True)
class Variable:
    """The fields of FMPy's ``ModelVariable`` that a run reads."""

    name: str
    valueReference: int
    type: str
    causality: str
    variability: str | None
    initial: str | None
    start: str | None
    description: str | None
    unit: str | None


@dataclass(frozen=True)
class CoSimulation:
    modelIdentifier: str


@dataclass(frozen=True)
class Description:
    """The part of FMPy's ``ModelDescription`` that a run reads, under the same names."""

    guid: str
    coSimulation: CoSimulation
    modelVariables: list[Variable]


@dataclass
class HeldFmu:
    """An FMU's extracted files in the cache, held (shared lock) until ``release``."""

    directory: Path
    description: Description
    _lock: int | None

    def release(self) -> None:
        if self._lock is not None:
            os.close(self._lock)
            self._lock = None


def cache_root() -> Path | None:
    """The cache folder (not created here); None when ``PLATOON_FMU_CACHE=off``."""
    chosen = os.environ.get(CACHE_ENV, "")
    if chosen == "off":
        return None
    if chosen:
        return Path(chosen)
    base = os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache"
    return Path(base) / "platoon-cosim" / "fmus"


def hold(fmu: Path, root: Path | None = None) -> HeldFmu | None:
    """The cached extraction of ``fmu``, made now if missing or damaged, held until released; None when
    the cache cannot serve this run (not writable, disabled, the entry damaged and in use elsewhere):
    the caller then extracts privately.

    Raises what extracting or reading the FMU raises (a bad zip, a model description failing the FMI
    schema), as a private extraction would.
    """
    root = cache_root() if root is None else root
    if root is None:
        return None
    data = Path(fmu).read_bytes()
    members = _members(data)
    if members is None:
        return None  # names zipfile would rewrite on extraction: not worth caching
    entry = root / f"{ENTRY_PREFIX}{Path(fmu).stem}-{hashlib.sha256(data).hexdigest()[:32]}"
    try:
        if not _private(root):
            return None
        for _ in range(_ATTEMPTS):
            lock = _hold_shared(entry)
            if lock is None:
                if not (entry / LOCK_NAME).exists():
                    _make(fmu, entry)
                continue
            try:
                description = _read_description(entry / DESCRIPTION)
                intact = description is not None and _intact(entry / FILES, members)
                if intact:
                    now = time.time_ns()  # last use, for eviction (the kernel's own stamp is ~4 ms coarse)
                    os.utime(entry / LOCK_NAME, ns=(now, now))
            except BaseException:
                os.close(lock)
                raise
            if intact:
                return HeldFmu(entry / FILES, description, lock)
            if not _discard(entry, lock):  # damaged, and another run has it open: leave it to them
                return None
    except OSError:
        return None  # e.g. no writable cache folder: extract privately, as before the cache
    return None


def _private(root: Path) -> bool:
    """Make the cache folder (only the user may write it) and check that it is ours: a folder others can
    write into could hold an FMU binary that is not the one we unzipped."""
    root.mkdir(mode=0o700, parents=True, exist_ok=True)
    status = os.stat(root)
    return status.st_uid == os.getuid() and not status.st_mode & 0o022


def _members(data: bytes) -> dict[str, tuple[int, int]] | None:
    """{relative path: (size, CRC-32)} of the zip's files, from its central directory."""
    with zipfile.ZipFile(io.BytesIO(data)) as archive:
        members = {}
        for info in archive.infolist():
            if info.is_dir():
                continue
            parts = info.filename.split("/")
            if any(part in ("", ".", "..") for part in parts) or "\\" in info.filename or ":" in info.filename:
                return None
            members[info.filename] = (info.file_size, info.CRC)
    return members


def _intact(folder: Path, members: dict[str, tuple[int, int]]) -> bool:
    for name, (size, crc) in members.items():
        try:
            with open(folder / name, "rb") as file:
                content = file.read(size + 1)
        except OSError:
            return False
        if len(content) != size or zlib.crc32(content) != crc:
            return False
    return True


def _hold_shared(entry: Path) -> int | None:
    """A shared lock on ``entry``'s lock file; None if there is no entry, or it was moved away (replaced,
    evicted) while we waited for the lock."""
    try:
        lock = os.open(entry / LOCK_NAME, os.O_RDWR)
    except FileNotFoundError:
        return None
    try:
        fcntl.flock(lock, fcntl.LOCK_SH)  # waits only while an entry is being moved away (one rename)
        held, now = os.fstat(lock), os.stat(entry / LOCK_NAME)
        if (held.st_dev, held.st_ino) == (now.st_dev, now.st_ino):
            return lock
    except FileNotFoundError:
        pass
    except BaseException:
        os.close(lock)
        raise
    os.close(lock)
    return None


def _make(fmu: Path, entry: Path) -> None:
    """Extract ``fmu`` aside, check its model description, publish it as ``entry``, evict old entries."""
    from fmpy import extract, read_model_description

    entry.parent.mkdir(parents=True, exist_ok=True)
    sweep()  # runs that find their FMUs cached make no temp folders; sweep dead runs' ones here
    maker = ScratchDir(entry.name, parent=entry.parent)  # also sweeps dead makers in the cache
    try:
        extract(str(fmu), str(maker.path / FILES))
        description = read_model_description(str(maker.path / FILES))  # the FMI schema check, once per entry
        _write_description(maker.path / DESCRIPTION, description)
    except BaseException:
        maker.remove()
        raise
    if maker.publish(entry):
        _evict(entry.parent)


def _write_description(path: Path, description: Any) -> None:
    record = {"guid": description.guid, "modelIdentifier": description.coSimulation.modelIdentifier,
              "variables": [{field: getattr(v, field) for field in _VARIABLE_FIELDS} for v in description.modelVariables]}
    path.write_text(json.dumps({"crc32": zlib.crc32(json.dumps(record, sort_keys=True).encode()), "record": record}))


def _read_description(path: Path) -> Description | None:
    """The entry's model description; None if missing or damaged."""
    try:
        stored = json.loads(path.read_bytes())
        record = stored["record"]
        if zlib.crc32(json.dumps(record, sort_keys=True).encode()) != stored["crc32"]:
            return None
        return Description(record["guid"], CoSimulation(record["modelIdentifier"]),
                           [Variable(**variable) for variable in record["variables"]])
    except (OSError, ValueError, KeyError, TypeError):
        return None


def _discard(entry: Path, lock: int) -> bool:
    """Remove ``entry`` if no other run holds it (``lock``, ours, is closed either way)."""
    try:
        fcntl.flock(lock, fcntl.LOCK_EX | fcntl.LOCK_NB)  # our shared lock becomes exclusive, or is lost
    except BlockingIOError:
        os.close(lock)
        return False
    # a scratch name: the sweep removes it once the lock is free, should this process die before rmtree
    away = entry.with_name(f"{PREFIX}discarded-{entry.name}-{os.urandom(6).hex()}")
    try:
        entry.rename(away)
    finally:
        os.close(lock)
    shutil.rmtree(away, ignore_errors=True)
    return True


def _evict(root: Path) -> None:
    """Remove the least recently used entries beyond ``KEEP`` that no run holds."""
    entries = []
    for folder in root.glob(f"{ENTRY_PREFIX}*"):
        try:
            entries.append((os.stat(folder / LOCK_NAME).st_mtime, folder))
        except OSError:
            continue
    entries.sort(reverse=True)
    for _, folder in entries[KEEP:]:
        try:
            _discard(folder, os.open(folder / LOCK_NAME, os.O_RDWR))
        except OSError:  # gone meanwhile, or not ours to remove: the bound is kept at the next chance
            continue
