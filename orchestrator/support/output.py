"""The one output rule every ``platoon`` command follows when it writes a file (docs/output.md).

1. A file is written to a temporary name *beside* its target (same folder, so same filesystem), synced
   (``fsync``) and renamed onto the target (``os.replace``, atomic) only once it is complete. A failure
   (full disk, permission, read-only filesystem, an exception) removes the temporary file: the old
   target stays as it was and no half file is left under any name a reader would take.
2. It never replaces one of the same command's inputs: compared by device and inode (``os.stat``
   follows symlinks; hard links share the inode), not by name, with or without ``--overwrite``.
3. It never replaces anything but a regular file: a FIFO, a device (``/dev/null`` as root!), a socket
   or a folder in the target's place is refused.
4. ``--overwrite`` means the same everywhere: without it, an existing non-empty file is replaced only if
   it is recognisably what the command writes (``kind``: e.g. an MCAP trace for ``platoon run``).

Every refusal or failure is an ``OutputError`` whose message is one line naming the path.
The trace writer's claim/aside/lock machinery (orchestrator/trace/output.py) builds on these checks.
"""

from __future__ import annotations

import os
import stat
import tempfile
from contextlib import contextmanager, suppress
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Iterable, Iterator, Optional

OVERWRITE_HELP = ("replace an existing output file that is not what this command writes "
                  "(never one of the command's inputs, never a FIFO, device or folder)")


class OutputError(ValueError):
    """An output path that must not (or cannot) be written; the message is one line for the user."""


def _kind_of(mode: int) -> str:
    if stat.S_ISDIR(mode):
        return "a folder"
    if stat.S_ISFIFO(mode):
        return "a FIFO"
    if stat.S_ISCHR(mode):
        return "a character device"
    if stat.S_ISBLK(mode):
        return "a block device"
    if stat.S_ISSOCK(mode):
        return "a socket"
    return "not a regular file"


def identity(path: Path) -> Optional[tuple[int, int]]:
    """(device, inode) of what ``path`` names, symlinks followed; None if it does not exist."""
    try:
        info = os.stat(path)
    except OSError:
        return None
    return info.st_dev, info.st_ino


def check_not_input(final: Path, protect: Iterable[Path], what: str = "--out") -> None:
    """Refuse ``final`` if it is (by device and inode) one of the command's inputs ``protect``."""
    mine = identity(final)
    if mine is None:
        return
    for kept in protect:
        if identity(Path(kept)) == mine:
            raise OutputError(f"{what} {final}: is the same file as {kept}, which this command reads; "
                              f"choose another path")


@dataclass(frozen=True)
class Kind:
    """What a command writes: ``test(path)`` recognises an existing file of it (replaced without
    ``--overwrite``); ``name`` says it in the refusal ("an MCAP trace")."""

    name: str
    test: Callable[[Path], bool]


def check_target(final: Path, overwrite: bool = False, protect: Iterable[Path] = (), what: str = "--out",
                 kind: Optional[Kind] = None) -> None:
    """Refuse a target this command must not replace (rules 2-4 above); returns if it may be written.

    An existing non-empty file is replaced only with ``overwrite`` or if ``kind`` recognises it.
    """
    final = Path(final)
    check_not_input(final, protect, what)
    try:
        info = os.stat(final)
    except FileNotFoundError:
        return
    except OSError as error:  # e.g. a path through a file (/proc/version/x.mcap)
        raise OutputError(f"{what} {final}: cannot write there: {error.strerror or error}") from None
    if not stat.S_ISREG(info.st_mode):
        raise OutputError(f"{what} {final}: is {_kind_of(info.st_mode)}, not a regular file; refusing to replace it"
                          + ("; give a file name" if stat.S_ISDIR(info.st_mode) else ""))
    if overwrite or info.st_size == 0 or (kind is not None and kind.test(final)):
        return
    raise OutputError(f"{what} {final}: exists and is not {kind.name if kind else 'empty'}; "
                      f"refusing to replace it (pass --overwrite to replace it anyway)")


def check_folder(folder: Path, protect: Iterable[Path] = (), what: str = "--out") -> None:
    """Refuse an output *folder* that exists as something else (a file, a FIFO, a device) or is an input."""
    check_not_input(folder, protect, what)
    try:
        mode = os.stat(folder).st_mode
    except FileNotFoundError:
        return
    except OSError as error:  # e.g. a path through a file (/proc/version/plots)
        raise OutputError(f"{what} {folder}: cannot write there: {error.strerror or error}") from None
    if not stat.S_ISDIR(mode):
        kind = "a file" if stat.S_ISREG(mode) else _kind_of(mode)
        raise OutputError(f"{what} {folder}: is {kind}, not a folder")


def _umask() -> int:
    mask = os.umask(0o022)
    os.umask(mask)
    return mask


def sync_folder(folder: Path) -> None:
    """fsync a folder, so that a rename (or removal) in it survives a power cut, not only its files' data."""
    with suppress(OSError):  # some filesystems refuse to open or sync a folder; the rename already happened
        fd = os.open(folder, os.O_RDONLY | os.O_DIRECTORY)
        try:
            os.fsync(fd)
        finally:
            os.close(fd)


def rename_into_place(aside: Path, final: Path) -> None:
    """The rule's last step: sync the complete file ``aside``, rename it onto ``final`` (atomic, same
    folder), then sync the folder (the rename itself reaches the disk). Every writer ends this way."""
    sync_file(aside)
    os.replace(aside, final)
    sync_folder(Path(final).parent)


def fail_line(what: str, final: Path, error: OSError) -> OutputError:
    """The one line for a write that failed: what, where, why, and that nothing was replaced."""
    return OutputError(f"{what} {final}: cannot write it: {error.strerror or error}; "
                       f"nothing was replaced and no partial file left")


@contextmanager
def replacing(final: Path, what: str = "--out", private: bool = False) -> Iterator[Path]:
    """Yield a temporary path beside ``final`` to write; on success sync it and rename it onto ``final``.

    On any exception the temporary file is removed and ``final`` is untouched; an ``OSError`` (full
    disk, permission ...) becomes an ``OutputError`` naming ``final``. Check the target first
    (``check_target``): this only writes. ``private``: the file stays 0600 from its creation on (a key).
    """
    final = Path(final)
    try:
        final.parent.mkdir(parents=True, exist_ok=True)
        fd, name = tempfile.mkstemp(prefix=f".{final.name}.", suffix=".tmp", dir=final.parent)
        if not private:
            os.fchmod(fd, 0o666 & ~_umask())  # mkstemp makes 0600; the file gets the mode open() would give it
        os.close(fd)
    except OSError as error:
        raise fail_line(what, final, error) from None
    aside = Path(name)
    try:
        yield aside
        rename_into_place(aside, final)
    except BaseException as error:
        with suppress(OSError):
            aside.unlink()
        if isinstance(error, OSError):
            raise fail_line(what, final, error) from None
        raise


def sync_file(path: Path) -> None:
    """fsync a written file (its data reaches the disk before it is renamed into place), or a folder."""
    fd = os.open(path, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def write_bytes(final: Path, data: bytes, what: str = "--out", private: bool = False) -> Path:
    """Write ``data`` to ``final`` by the rule (temporary name, sync, rename). Check the target first."""
    with replacing(final, what, private) as aside:
        with open(aside, "wb") as stream:
            stream.write(data)
    return final


def write_text(final: Path, text: str, what: str = "--out") -> Path:
    return write_bytes(final, text.encode(), what)


def starts_with(*magics: bytes) -> Callable[[Path], bool]:
    """A ``kind`` test: the file starts with one of ``magics`` (what a command's own output starts with)."""
    def test(path: Path) -> bool:
        try:
            with open(path, "rb") as stream:
                head = stream.read(max(len(m) for m in magics))
        except OSError:
            return False
        return any(head.startswith(m) for m in magics)
    return test


IMAGE_MAGIC = {".png": (b"\x89PNG\r\n\x1a\n",), ".pdf": (b"%PDF-",), ".svg": (b"<?xml", b"<svg")}


def _is_image(path: Path) -> bool:
    return starts_with(*IMAGE_MAGIC.get(path.suffix.lower(), IMAGE_MAGIC[".png"]))(path)


IMAGE = Kind("an image (PNG, PDF or SVG, as its suffix says)", _is_image)


@dataclass(frozen=True)
class OwnFiles:
    """The rule for a command whose files have names of its own in the folder it is given (``platoon
    build --out``: Vehicle.fmu, native/Vehicle.fmu ...): such a file is replaced whatever it holds (a
    damaged FMU is rebuilt; the names are the command's, so no ``--overwrite``), but never one of the
    command's inputs (``protect``), never a FIFO, device or folder in its place, and only by a complete,
    synced file renamed onto it. The builders call ``check`` before they read a target and ``replacing``
    to write it (fmus/builders/base.py: ``Output``). The FMUs a run builds for itself into build/fmus
    follow it too (orchestrator/components/kinds.py: ``ensure_fmus``)."""

    protect: tuple[Path, ...] = ()
    what: str = "--out"

    def check(self, target: Path) -> None:
        check_folder(Path(target).parent, (), self.what)
        check_target(target, overwrite=True, protect=self.protect, what=self.what)

    def replacing(self, target: Path):  # a context manager yielding the aside path (``replacing`` above)
        return replacing(target, self.what)
