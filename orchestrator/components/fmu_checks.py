"""FMUs found current and whole before, known again by their files' stamps: a run skips the builder's check.

Before every run, ``Builder.build`` (fmus/builders/base.py) decides whether each FMU must be rebuilt: it
computes the GUID the sources give (a SHA-256 of every C source, bundled Python module, builder module and
FMI header, and pythonfmu's version, read through ``importlib.metadata``), opens the archive, compares its
GUID and tests every entry's CRC. That is ~13 ms of a 10-step run, the same answer run after run
(docs/performance.md, "Start-up"). Here the answer is kept under ``~/.cache/platoon-cosim/fmu-checks/`` and
given again while nothing it was computed from has changed:

* **the FMU file is the same file**: device, inode, size, modification and change time as when it was
  checked (or written by the build). Any write through the file system changes the change time (which no
  program can set back); a file copied or renamed into place has another inode. So an FMU replaced,
  truncated, edited or stripped of its binary is checked again, and rebuilt as before.
* **the sources are the same**: the size and modification time of every file its GUID is a digest of
  (``Builder.digest_files``), the modification time of the folders whose modules every FMU carries (a
  module added or removed changes the GUID), and of the folder pythonfmu is installed in (installing
  another pythonfmu replaces its metadata folder there), with pythonfmu's own version.

What this gives up: a byte of the archive damaged without a write through the file system (a failing
disk) is no longer caught by the CRC test before the run. It is caught one step later all the same: the
run opens the FMU through the cache of extracted FMUs (orchestrator/components/cache.py), which names its
entries by the SHA-256 of the FMU file and extracts a new one through ``zipfile``, which tests each entry's
CRC as it reads it; a damaged archive then stops the run with an error instead of being rebuilt.

A cache folder that cannot be written is no error: the FMUs are checked each time, as without it.
"""

from __future__ import annotations

import json
import os
import stat
import sys
import zlib
from pathlib import Path
from typing import TYPE_CHECKING, Any

from orchestrator.support.cache_files import cache_folder, modified, stamps, write_whole

if TYPE_CHECKING:
    from fmus.builders import Builder, BuiltFmu

FORMAT = 1  # of the entries; an entry of another format is not read


def identity(path: Path) -> list[int] | None:
    """What tells a regular file from any other that took its place: device, inode, size, modification
    and change time; None when ``path`` is not a regular file."""
    try:
        status = os.stat(path)
    except OSError:
        return None
    if not stat.S_ISREG(status.st_mode):
        return None
    return [status.st_dev, status.st_ino, status.st_size, status.st_mtime_ns, status.st_ctime_ns]


def _entry_path(builder: "Builder", folder: Path) -> tuple[Path, str]:
    key = f"{builder.kind} {builder.fmi_version} {os.path.abspath(folder)}"
    return cache_folder("fmu-checks") / f"{builder.kind}{builder.fmi_version}-{zlib.crc32(key.encode()):08x}.json", key


def sources_stamp(builder: "Builder", name: str) -> dict[str, Any]:
    """What FMU ``name``'s GUID depends on, as stamps (taken before the check: a source that changes during
    it leaves stamps that no longer match)."""
    from fmus.builders.pythonfmu import BUNDLED_FOLDERS

    pythonfmu = sys.modules["pythonfmu"]  # imported by fmus.builders, on purpose (see fmus/builders/pythonfmu.py)
    folders = [*BUNDLED_FOLDERS, Path(pythonfmu.__file__).parent.parent]
    return {"files": stamps(str(path) for path in builder.digest_files(name)),
            "folders": {str(folder): modified(folder) for folder in folders},
            "pythonfmu": getattr(pythonfmu, "__version__", None)}


def _stored(path: Path, key: str) -> dict[str, Any] | None:
    """The entry at ``path`` when it is one of this format for ``key``; None when absent, unreadable or another's."""
    try:
        entry = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return None
    if not isinstance(entry, dict) or entry.get("format") != FORMAT or entry.get("key") != key:
        return None
    return entry


def known_current(builder: "Builder", folder: Path, names: tuple[str, ...]) -> list["BuiltFmu"] | None:
    """FMUs ``names`` in ``folder`` as ``builder.build`` would return them (none rebuilt), when each was found
    current and whole before and neither it nor anything its GUID depends on changed since; else None."""
    from fmus.builders import BuiltFmu

    entry = _stored(*_entry_path(builder, folder))
    if entry is None:
        return None
    found = []
    for name in names:
        known = entry.get("fmus", {}).get(name)
        fmu = Path(folder) / f"{name}.fmu"
        if not isinstance(known, dict) or known.get("identity") != identity(fmu) \
                or known.get("sources") != sources_stamp(builder, name):
            return None
        found.append(BuiltFmu(name, fmu, known["guid"], rebuilt=False))
    return found


def remember(builder: "Builder", folder: Path, built: list["BuiltFmu"], sources: dict[str, dict[str, Any]],
             before: dict[str, list[int] | None]) -> None:
    """Keep the verdict of ``builder.build`` on ``built``: ``sources`` and ``before`` (each FMU's identity)
    were taken before it checked them. An FMU it found current is kept only if it is still the file it
    checked; one it rebuilt, as written."""
    path, key = _entry_path(builder, folder)
    entry = _stored(path, key) or {}
    fmus = entry.get("fmus") if isinstance(entry.get("fmus"), dict) else {}
    for fmu in built:
        now = identity(fmu.path)
        if now is None or (not fmu.rebuilt and now != before.get(fmu.name)):
            fmus.pop(fmu.name, None)
            continue
        fmus[fmu.name] = {"identity": now, "guid": fmu.guid, "sources": sources[fmu.name]}
    write_whole(path, json.dumps({"format": FORMAT, "key": key, "fmus": fmus}))
