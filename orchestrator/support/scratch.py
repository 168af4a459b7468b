"""Temporary folders that do not outlive their process for long, even one killed with SIGKILL.

A run extracts its FMUs into a temporary folder and removes it when it ends; a SIGKILL (or a crash)
skips that, and every such run used to leave its folders in the temp directory forever. Each folder
made here holds an exclusive ``flock`` on a lock file inside it for as long as its owner lives; the
kernel drops the lock when the owner dies, however it dies. Whenever a new folder is made, the
folders of dead owners (lock free) are swept. ``flock`` needs no pid, so a reused pid or a process
in another pid namespace sharing /tmp is never mistaken for the owner, or for a dead one.
"""

from __future__ import annotations

import fcntl
import os
import shutil
import tempfile
import time
from pathlib import Path

PREFIX = "platoon-scratch-"
MAKING = "platoon-making-"  # a folder is made under this name and renamed once its lock is held
LOCK_NAME = ".owner.lock"
# A folder still under MAKING this long after it was made lost its owner between mkdtemp and rename.
MAKING_GRACE = 60.0  # s


class ScratchDir:
    """A folder in the temp directory (or in ``parent``), held by this process until ``remove`` or
    ``publish`` (or its death)."""

    def __init__(self, label: str, parent: Path | None = None) -> None:
        sweep(parent)
        making = Path(tempfile.mkdtemp(prefix=f"{MAKING}{label}-", dir=parent))
        self._lock: int | None = os.open(making / LOCK_NAME, os.O_CREAT | os.O_RDWR, 0o600)
        fcntl.flock(self._lock, fcntl.LOCK_EX)
        # every folder under PREFIX is locked from the moment it appears: a free lock means a dead owner
        self.path = making.with_name(PREFIX + making.name[len(MAKING):])
        making.rename(self.path)
        self._published = False

    def publish(self, target: Path) -> bool:
        """Rename the folder to ``target`` (a name no sweep matches) and give it up: from now on it is not
        scratch, nothing here removes it. False, and the folder removed, if ``target`` exists already
        (another process published the same thing first). The lock file goes along (``.owner.lock``)."""
        try:
            self.path.rename(target)  # atomic; fails on an existing non-empty folder
        except OSError:
            self.remove()
            return False
        self.path = target
        if self._lock is not None:
            os.close(self._lock)
            self._lock = None
        self._published = True
        return True

    def remove(self) -> None:
        if self._published:
            return
        shutil.rmtree(self.path, ignore_errors=True)
        if self._lock is not None:
            os.close(self._lock)  # after the folder is gone: no sweeper can take it for a dead one
            self._lock = None

    def __enter__(self) -> Path:
        return self.path

    def __exit__(self, *exc: object) -> None:
        self.remove()


def sweep(temp_dir: str | Path | None = None) -> list[Path]:
    """Remove the scratch folders whose owner is dead; returns them."""
    removed = []
    folder_of = Path(temp_dir or tempfile.gettempdir())
    for folder in [*folder_of.glob(f"{PREFIX}*"), *folder_of.glob(f"{MAKING}*")]:
        if folder.is_symlink() or not folder.is_dir() or _owner_alive(folder):
            continue
        shutil.rmtree(folder, ignore_errors=True)
        removed.append(folder)
    return removed


def _owner_alive(folder: Path) -> bool:
    if folder.name.startswith(MAKING):  # renamed within microseconds unless its owner died meanwhile
        try:
            return time.time() - folder.stat().st_mtime < MAKING_GRACE
        except OSError:
            return True  # gone already
    try:
        lock = os.open(folder / LOCK_NAME, os.O_RDWR)
    except FileNotFoundError:  # not made here (no lock file ever): leave it alone
        return True
    except OSError:  # not ours to judge (another user's folder)
        return True
    try:
        fcntl.flock(lock, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except BlockingIOError:
        return True  # the owner holds it
    finally:
        os.close(lock)  # also releases the lock if we took it
    return False
