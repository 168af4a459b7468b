"""What every FMU builder shares: the ``Builder`` protocol (build what is stale, check what is whole),
reproducible archives and the FMUs' names and folders.

A builder makes one kind of FMU (pythonfmu, native FMI 2.0, native FMI 3.0: ``fmus.builders``). The
three differ only in how an FMU's GUID is derived (``expected_guid``), which entries a whole FMU holds
(``required_entries``) and how one is made (``build_one``); deciding what to rebuild, checking an
archive and writing it reproducibly are done here, once.
"""

from __future__ import annotations

import importlib
import os
import zipfile
import zlib
from abc import ABC, abstractmethod
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, ContextManager, Protocol
from xml.etree import ElementTree

# the fmus/ folder, not fmus.__file__: an FMU run in this process first may have imported the
# package from its resources folder (which holds neither this file nor, after the run, anything)
PACKAGE_DIR = Path(__file__).resolve().parent.parent
ROOT = PACKAGE_DIR.parent  # the folder holding fmus/, bridge/ and orchestrator/ (repository or site-packages)
FMU_NAMES = ("Vehicle", "VirtualTarget")  # what every run uses
LIVE_FMU = "LiveVehicle"  # a live robot as an FMU (platoon build --live, platoon export-ssp of a live config)
LINK_FMU = "Link"  # a communication link, in runs whose config has a [links] table (docs/links.md)
REMOTE_FMU = "RemoteVehicle"  # a client of a `platoon serve` as an FMU (platoon export-ssp of a remote config)
ALL_FMUS = FMU_NAMES + (LINK_FMU, LIVE_FMU, REMOTE_FMU)
DEFAULT_OUT = Path("build") / "fmus"
_ZIP_TIME = (2020, 1, 1, 0, 0, 0)


@dataclass(frozen=True)
class BuiltFmu:
    name: str
    path: Path
    guid: str  # the FMI 2.0 guid or FMI 3.0 instantiationToken
    rebuilt: bool


class BuildError(RuntimeError):
    """An FMU cannot be built in this process (the message says why and what to do)."""


class Builder(ABC):
    """Builds one kind of FMU into a folder, each FMU only when it is missing, stale or damaged."""

    kind: str  # "python" or "native": what a run's --fmus names
    fmi_version: int  # 2 or 3
    default_out: Path  # where `platoon build` puts this kind

    @abstractmethod
    def expected_guid(self, name: str) -> str:
        """The GUID (instantiationToken) FMU ``name`` gets from the sources in this checkout."""

    @abstractmethod
    def digest_files(self, name: str) -> list[Path]:
        """The files whose contents the GUID of FMU ``name`` is a digest of (with pythonfmu's version, and the
        builder's constants, which live in these files): what a cached verdict on the FMU depends on."""

    @abstractmethod
    def required_entries(self, name: str) -> set[str]:
        """The archive entries without which FMU ``name`` is not a whole build for this machine."""

    @abstractmethod
    def build_one(self, name: str, guid: str) -> dict[str, bytes]:
        """Build FMU ``name`` with ``guid``: its archive's entries (``build`` writes them)."""

    def is_complete(self, path: Path, name: str, guid: str) -> bool:
        """True when ``path`` is a whole, intact build of ``name`` with ``guid``: every entry passes its
        CRC, and it holds the model description with that GUID and every required entry. The GUID alone
        does not make an FMU runnable (a copy stripped of its binary has it too)."""
        return archive_is_whole(path, guid, self.required_entries(name))

    def build(self, out_dir: Path | None = None, force: bool = False,
              names: tuple[str, ...] = FMU_NAMES,
              announce: Callable[[str, Path], None] | None = None, output: Output | None = None) -> list[BuiltFmu]:
        """FMUs ``names`` in ``out_dir`` (default: ``default_out``), each built unless a current one is
        there already, or always with ``force``; ``announce(name, folder)`` before each build (a build
        takes seconds: the caller says so). ``output``: the orchestrator's output rule (checks each
        target before reading it, writes it aside and renames it); by default an FMU is written aside
        and renamed into place (``write_fmu``)."""
        folder = Path(self.default_out if out_dir is None else out_dir)
        built = []
        for name in names:
            guid = self.expected_guid(name)
            path = folder / f"{name}.fmu"
            if output is not None:
                output.check(path)  # before reading it: a FIFO in its place would block the zip reader
            if not force and path.exists() and self.is_complete(path, name, guid):
                built.append(BuiltFmu(name, path, guid, rebuilt=False))
            else:
                if announce is not None:
                    announce(name, folder)
                entries = self.build_one(name, guid)
                write_fmu(path, entries, output.replacing if output is not None else None)
                built.append(BuiltFmu(name, path, guid, rebuilt=True))
        return built


class Output(Protocol):
    """Where a builder may write, and how (orchestrator/support/output.py: ``OwnFiles``)."""

    def check(self, target: Path) -> None:
        """Raise (an ``OSError`` or ``ValueError`` subclass, one line) if ``target`` must not be replaced."""

    def replacing(self, target: Path) -> ContextManager[Path]:
        """A temporary path beside ``target`` to write, renamed onto it when complete and synced."""


def source_files() -> tuple[Path, ...]:
    """What a build reads: every file of the fmus package (slaves, models, C sources, builders). The
    output rule never lets a build replace one of them (``Output.check``, ``protect``)."""
    return tuple(path for path in PACKAGE_DIR.rglob("*") if path.is_file() and "__pycache__" not in path.parts)


def fmu_guid(path: Path) -> str | None:
    """GUID (FMI 2.0) or instantiationToken (FMI 3.0) recorded in an FMU's model description, or None if unreadable."""
    try:
        with zipfile.ZipFile(path) as archive:
            root = ElementTree.fromstring(archive.read("modelDescription.xml"))
    except (OSError, KeyError, zipfile.BadZipFile, zlib.error, ElementTree.ParseError):
        return None
    return root.get("guid") or root.get("instantiationToken")  # FMI 2.0, FMI 3.0


def archive_is_whole(path: Path, guid: str, required: set[str]) -> bool:
    """``path`` has ``guid``, every entry of ``required`` (not empty) and passes every CRC. Anything but a
    regular file is no FMU (and is never opened: reading a FIFO would block until someone writes to it)."""
    if not path.is_file():
        return False
    if fmu_guid(path) != guid:
        return False
    try:
        with zipfile.ZipFile(path) as archive:
            sizes = {item.filename: item.file_size for item in archive.infolist()}
            return all(sizes.get(entry, 0) > 0 for entry in required) and archive.testzip() is None
    except (OSError, zipfile.BadZipFile, zlib.error):  # zlib.error: a damaged deflate stream, before its CRC
        return False


def slave_instance(name: str):
    """An instance of slave class ``name`` (fmus/slaves), whose declarations every builder describes."""
    module = importlib.import_module(f"fmus.slaves.{name}")
    return getattr(module, name)(instance_name="modelDescription")


def _zip_entry(name: str) -> zipfile.ZipInfo:
    info = zipfile.ZipInfo(name, date_time=_ZIP_TIME)
    info.compress_type = zipfile.ZIP_DEFLATED
    info.external_attr = 0o644 << 16
    return info


def write_fmu(target: Path, entries: dict[str, bytes],
              replacing: Callable[[Path], ContextManager[Path]] | None = None) -> Path:
    """Write an FMU archive reproducibly (sorted entries, fixed timestamps) aside, then move it into place
    (``replacing``: the output rule's way, which also syncs it; by default a rename)."""
    if replacing is not None:
        with replacing(target) as partial, zipfile.ZipFile(partial, "w") as archive:
            for entry in sorted(entries):
                archive.writestr(_zip_entry(entry), entries[entry])
        return target
    target.parent.mkdir(parents=True, exist_ok=True)
    # one name per process: two runs that find the FMUs out of date build them side by side, each
    # renaming its own complete file into place (the last one wins; both are the same FMU)
    partial = target.with_name(f"{target.name}.{os.getpid()}.partial")
    try:
        with zipfile.ZipFile(partial, "w") as archive:
            for entry in sorted(entries):
                archive.writestr(_zip_entry(entry), entries[entry])
        partial.replace(target)  # never leave a half-written FMU under the final name
    except BaseException:  # e.g. a full disk: no half-written .partial left behind either
        partial.unlink(missing_ok=True)
        raise
    return target
