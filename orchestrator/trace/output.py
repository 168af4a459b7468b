"""Where a trace file goes: claim its path, write it aside, put it in place only once it is finalized.

A trace is written to its *aside file* ``<trace>.partial`` in the same folder and renamed onto
``<trace>`` (``os.replace``, atomic) only after its footer is written. So a killed run never damages
what was at ``<trace>`` before (its unfinished data stays in the aside file, for ``platoon trace
recover``), and a reader never sees a half-written file under the final name.

The aside file is also the lock: the run holds an exclusive ``fcntl.flock`` on it for as long as it
writes (the trace writer process holds a duplicate of the descriptor: TraceProcess.share), and the operating system drops the lock
when the process dies, however it dies. A second run on the same path finds it locked and refuses;
there is no check-then-write window. The same rules serve ``trace recover --out``
(docs/trace-format.md, "Where a trace is written").
"""

from __future__ import annotations

import fcntl
import os
from dataclasses import dataclass
from itertools import count
from pathlib import Path
from typing import Iterable

from .format import MAGIC

ASIDE_SUFFIX = ".partial"


from orchestrator.support.output import Kind, OutputError, check_target, rename_into_place

__all__ = ["OutputError", "Claim", "aside_path", "check_in_use", "check_replaceable", "claim", "claim_new", "publish"]


def aside_path(final: Path, suffix: str = ASIDE_SUFFIX) -> Path:
    """The aside file a trace is written to before it is put in place: ``<trace>.partial``."""
    return final.with_name(final.name + suffix)


def is_mcap(path: Path) -> bool:
    """True if ``path`` starts with the MCAP magic (a trace, finished or not)."""
    try:
        with open(path, "rb") as stream:
            return stream.read(len(MAGIC)) == MAGIC
    except OSError:
        return False


def check_replaceable(final: Path, overwrite: bool = False, protect: Iterable[Path] = (), what: str = "--out") -> None:
    """Refuse an output path whose current content must not be replaced.

    Never any of ``protect`` (e.g. the run's own config, a recovery's input), whatever ``overwrite``
    says; a file that is not an MCAP trace (and not empty) only with ``overwrite``; never a folder.
    """
    check_target(final, overwrite, protect, what, kind=TRACE)


@dataclass
class Claim:
    """A claimed output path: the aside file is created, truncated and locked by this process."""

    final: Path
    aside: Path
    fd: int

    @property
    def published(self) -> bool:
        """True once the aside file was renamed onto the final path."""
        return not self.aside.exists() and self.final.exists()

    def where(self) -> Path:
        """Where the data is now: the final path once published, else the aside file (if any)."""
        return self.final if self.published or not self.aside.exists() else self.aside

    def release(self) -> None:
        """Drop the lock (closing the descriptor); idempotent."""
        if self.fd >= 0:
            os.close(self.fd)
            self.fd = -1


def publish(aside: Path, final: Path) -> None:
    """Put a finalized file in place: synced, then one atomic rename in the same folder, then the folder
    synced (support/output.py: ``rename_into_place``)."""
    rename_into_place(aside, final)


def check_in_use(path: Path) -> None:
    """Refuse a file that a running run holds locked (an aside file being written)."""
    try:
        fd = os.open(path, os.O_RDONLY | os.O_CLOEXEC)
    except OSError:
        return
    try:
        fcntl.flock(fd, fcntl.LOCK_SH | fcntl.LOCK_NB)
    except BlockingIOError:
        raise OutputError(f"trace {path}: a running run is writing it right now; wait for it to end") from None
    finally:
        os.close(fd)


def _lock(aside: Path, exclusive_create: bool) -> int | None:
    """Open and lock ``aside``; None if ``exclusive_create`` and it already exists. Raises OutputError if locked."""
    flags = os.O_RDWR | os.O_CREAT | os.O_CLOEXEC | (os.O_EXCL if exclusive_create else 0)
    while True:
        try:
            fd = os.open(aside, flags, 0o644)
        except FileExistsError:
            return None
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            os.close(fd)
            raise OutputError(f"{aside.with_suffix('')}: another process is writing this file right now "
                              f"(its aside file {aside} is locked); choose another --out") from None
        try:
            current = os.stat(aside)
        except FileNotFoundError:
            current = None
        mine = os.fstat(fd)
        if current is not None and (current.st_dev, current.st_ino) == (mine.st_dev, mine.st_ino):
            return fd
        os.close(fd)  # the previous writer renamed it into place meanwhile: take a fresh aside file


def claim(final: str | Path, overwrite: bool = False, protect: Iterable[Path] = (), what: str = "--out",
          suffix: str = ASIDE_SUFFIX) -> Claim:
    """Claim ``final`` for writing: checks (``check_replaceable``), then lock its aside file and empty it.

    A non-empty aside file left by a killed run holds its unfinished trace: refused unless
    ``overwrite`` (recover it first). Raises ``OutputError`` with a one-line reason.
    """
    final = Path(final)
    protect = list(protect)
    check_replaceable(final, overwrite, protect, what)
    aside = aside_path(final, suffix)
    check_target(aside, True, protect, f"{what} {final}: its aside file")
    try:
        final.parent.mkdir(parents=True, exist_ok=True)
        fd = _lock(aside, exclusive_create=False)
    except OSError as error:
        raise OutputError(f"{what} {final}: cannot write the trace there: {error.strerror or error}") from None
    assert fd is not None
    if os.fstat(fd).st_size > 0 and not overwrite:
        os.close(fd)
        raise OutputError(f"{what} {final}: {aside} holds the unfinished trace of an earlier run (killed?); "
                          f"recover it with `platoon trace recover {aside}`, or pass --overwrite to discard it")
    os.ftruncate(fd, 0)
    return Claim(final, aside, fd)


def claim_new(folder: Path, stem: str, suffix: str = ".mcap") -> Claim:
    """Claim a fresh path ``folder/stem.mcap`` (or ``stem-2.mcap``, ``-3`` ...) that no file or run uses.

    Race-free: the aside file is created with O_EXCL, and the final path is checked only after that
    (a finished run renames its aside file onto the final path atomically, so one of the two is seen).
    """
    try:
        folder.mkdir(parents=True, exist_ok=True)
        for number in count(1):
            final = folder / f"{stem}{'' if number == 1 else f'-{number}'}{suffix}"
            aside = aside_path(final)
            fd = _lock(aside, exclusive_create=True)
            if fd is None:
                continue
            if final.exists():
                os.close(fd)
                aside.unlink()
                continue
            return Claim(final, aside, fd)
    except OSError as error:
        raise OutputError(f"trace folder {folder}: cannot write there: {error.strerror or error}") from None
    raise AssertionError("unreachable")


TRACE = Kind("an MCAP trace", is_mcap)  # what `platoon run` and `trace recover` replace without --overwrite
