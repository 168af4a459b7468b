"""`platoon build`: package the slaves as FMI 2.0 co-simulation FMUs with pythonfmu, then finish them.

pythonfmu lays out the archive (its runtime binary, its Python glue, the slave script). We then
replace its model description with a complete one, add documentation/index.html and the model
package as resources, and write the archive reproducibly (sorted entries, fixed timestamps). The
GUID is derived from a digest of every bundled source, so an FMU is rebuilt exactly when a source
changes and a trace can name the model version it ran.
"""

from __future__ import annotations

import hashlib
import os
import importlib.metadata
import importlib
import sys
import tempfile
import zipfile
from dataclasses import dataclass
from pathlib import Path
from typing import Callable
from xml.etree import ElementTree

# Imported here, first, on purpose: our FMUs run in the host's interpreter, and if one runs before
# anything imported pythonfmu, it imports pythonfmu from the FMU's resources folder, a copy without
# the runtime binaries that the builder copies into every FMU (see _builder). It costs nothing extra:
# the FMUs' slaves import pythonfmu in every run anyway.
import pythonfmu  # noqa: F401

import fmus
from fmus.modeldescription import guid_for, model_description

# this file's own folder, not fmus.__file__: an FMU run in this process first may have imported the
# package from its resources folder (which holds neither this file nor, after the run, anything)
PACKAGE_DIR = Path(__file__).resolve().parent
FMU_NAMES = ("Vehicle", "VirtualTarget")  # what every run uses
LIVE_FMU = "LiveVehicle"  # a live robot as an FMU (platoon build --live, platoon export-ssp of a live config)
ALL_FMUS = FMU_NAMES + (LIVE_FMU,)
DEFAULT_OUT = Path("build") / "fmus"
_ZIP_TIME = (2020, 1, 1, 0, 0, 0)
_BUNDLED_SUBPACKAGES = ("model", "slaves")
_ROOT = PACKAGE_DIR.parent  # the folder holding fmus/, bridge/ and orchestrator/ (repository or site-packages)
# What an FMU carries beyond fmus/model and fmus/slaves: the LiveVehicle FMU runs the bridge's host side
# (bridge.live and what it imports) and the orchestrator's pacer, so it needs nothing but zenoh installed.
_ONLY_IN = {"LiveVehicle.py": LIVE_FMU}
_EXTRA_SOURCES = {
    LIVE_FMU: ("bridge/__init__.py", "bridge/claim.py", "bridge/live.py", "bridge/protocol.py", "bridge/session.py", "bridge/states.py",
               "orchestrator/__init__.py", "orchestrator/interface.py", "orchestrator/errors.py",
               "orchestrator/realtime.py"),
}


@dataclass(frozen=True)
class BuiltFmu:
    name: str
    path: Path
    guid: str
    rebuilt: bool


def bundled_sources(name: str = "Vehicle") -> list[Path]:
    """The package files FMU ``name`` carries as resources (its code must need nothing else)."""
    files = [PACKAGE_DIR / "__init__.py"]
    for sub in _BUNDLED_SUBPACKAGES:
        files += sorted(path for path in (PACKAGE_DIR / sub).glob("*.py") if _ONLY_IN.get(path.name, name) == name)
    return files + [_ROOT / extra for extra in _EXTRA_SOURCES.get(name, ())]


def source_digest(name: str = "Vehicle") -> str:
    """Digest of everything that shapes FMU ``name``: bundled sources, builder modules, pythonfmu version."""
    digest = hashlib.sha256(importlib.metadata.version("pythonfmu").encode())
    for path in bundled_sources(name) + [PACKAGE_DIR / "build.py", PACKAGE_DIR / "modeldescription.py",
                                         PACKAGE_DIR / "documentation.py"]:
        digest.update(str(path.relative_to(PACKAGE_DIR) if path.is_relative_to(PACKAGE_DIR)
                          else path.relative_to(_ROOT)).encode())
        digest.update(path.read_bytes())
    return digest.hexdigest()


def expected_guid(name: str) -> str:
    return guid_for(source_digest(name), name)


def fmu_guid(path: Path) -> str | None:
    """GUID (FMI 2.0) or instantiationToken (FMI 3.0) recorded in an FMU's model description, or None if unreadable."""
    try:
        with zipfile.ZipFile(path) as archive:
            root = ElementTree.fromstring(archive.read("modelDescription.xml"))
    except (OSError, KeyError, zipfile.BadZipFile, ElementTree.ParseError):
        return None
    return root.get("guid") or root.get("instantiationToken")  # FMI 2.0, FMI 3.0


def fmi_platform() -> tuple[str, str]:
    """This machine's FMI 2 binaries folder and shared-library suffix ("linux64", ".so"): FMPy's
    ``platform`` and ``sharedLibraryExtension``, without importing FMPy, which a run of the native
    engine no longer needs (~0.04 s of start-up; tests/test_startup.py checks that they agree)."""
    import platform as host

    system, suffix = next(((name, ext) for prefix, name, ext in (("win", "win", ".dll"), ("linux", "linux", ".so"),
                                                                  ("darwin", "darwin", ".dylib"))
                           if sys.platform.startswith(prefix)), (sys.platform, ""))
    wide = host.machine().lower() in {"aarch64", "arm64"} or sys.maxsize > 2**32
    return system + ("64" if wide else "32"), suffix


def is_complete(path: Path, name: str, guid: str) -> bool:
    """True when ``path`` is a whole, intact build of ``name`` with ``guid``: every entry passes its CRC,
    and it holds the model description with that GUID, the binary for this platform and the bundled
    sources. The GUID alone does not make an FMU runnable (a copy stripped of its binary has it too)."""
    platform, suffix = fmi_platform()
    required = {f"binaries/{platform}/{name}{suffix}", f"resources/{name}.py"}
    required |= {f"resources/{source.relative_to(_ROOT).as_posix()}" for source in bundled_sources(name)}
    return archive_is_whole(path, guid, required)


def archive_is_whole(path: Path, guid: str, required: set[str]) -> bool:
    """``path`` has ``guid``, every entry of ``required`` (not empty) and passes every CRC."""
    if fmu_guid(path) != guid:
        return False
    try:
        with zipfile.ZipFile(path) as archive:
            sizes = {item.filename: item.file_size for item in archive.infolist()}
            return all(sizes.get(entry, 0) > 0 for entry in required) and archive.testzip() is None
    except (OSError, zipfile.BadZipFile):
        return False


def _slave_instance(name: str):
    module = importlib.import_module(f"fmus.slaves.{name}")
    return getattr(module, name)(instance_name="modelDescription")


def _zip_entry(name: str) -> zipfile.ZipInfo:
    info = zipfile.ZipInfo(name, date_time=_ZIP_TIME)
    info.compress_type = zipfile.ZIP_DEFLATED
    info.external_attr = 0o644 << 16
    return info


class BuildError(RuntimeError):
    """An FMU cannot be built in this process (the message says why and what to do)."""


def _builder() -> type:
    """pythonfmu's FmuBuilder, from a pythonfmu that carries its runtime binaries.

    An FMU run in this process before (FMPy loading one of ours) imports ``pythonfmu`` from the FMU's
    resources folder when nothing imported it earlier; that copy has no binaries, and its builder
    would write FMUs without any. Refuse instead of writing a broken FMU.
    """
    from pythonfmu import builder

    binaries = Path(builder.__file__).resolve().parent / "resources" / "binaries"
    if not any(binaries.rglob("*.so")) and not any(binaries.rglob("*.dll")) and not any(binaries.rglob("*.dylib")):
        raise BuildError(f"pythonfmu was imported from {Path(builder.__file__).parent}, which has no runtime "
                         f"binaries (an FMU's resources folder?); build the FMUs in a fresh process: platoon build")
    return builder.FmuBuilder


def _build_one(name: str, out_dir: Path, guid: str) -> Path:
    from fmus.documentation import documentation_html  # only to build (html.entities: start-up time of every run)

    version = fmus.__version__
    FmuBuilder = _builder()  # only to build: checking that FMUs are current needs none of pythonfmu

    with tempfile.TemporaryDirectory(prefix="platoon-build-") as scratch:
        # pythonfmu imports the script by its stem from the script's folder.
        sys.path.insert(0, str(PACKAGE_DIR / "slaves"))
        try:
            raw = FmuBuilder.build_FMU(PACKAGE_DIR / "slaves" / f"{name}.py", dest=scratch)
        finally:
            sys.path.remove(str(PACKAGE_DIR / "slaves"))
            sys.modules.pop(name, None)
        slave = _slave_instance(name)
        entries: dict[str, bytes] = {}
        with zipfile.ZipFile(raw) as archive:
            for item in archive.infolist():
                if item.filename != "modelDescription.xml" and not item.is_dir():
                    entries[item.filename] = archive.read(item)
    if not any(entry.startswith("binaries/") for entry in entries):
        raise BuildError(f"{name}.fmu: pythonfmu's builder produced no binaries; the FMU was not written")
    for path in bundled_sources(name):
        entries[f"resources/{path.relative_to(_ROOT).as_posix()}"] = path.read_bytes()
    entries["modelDescription.xml"] = model_description(slave, guid, version)
    entries["documentation/index.html"] = documentation_html(slave, version).encode()

    return write_fmu(out_dir / f"{name}.fmu", entries)


def write_fmu(target: Path, entries: dict[str, bytes]) -> Path:
    """Write an FMU archive reproducibly (sorted entries, fixed timestamps) aside, then move it into place."""
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


def build_stale(out_dir: Path, force: bool, names: tuple[str, ...], guid_of: Callable[[str], str],
                is_current: Callable[[Path, str, str], bool], build: Callable[[str, str, Path], Path]) -> list[BuiltFmu]:
    """FMUs ``names`` in ``out_dir``, each built by ``build(name, guid, out_dir)`` unless a current one
    (``is_current(path, name, guid)`` for ``guid_of(name)``) is there already, or always with ``force``.
    The pythonfmu, native and FMI 3.0 builders differ only in these three functions."""
    built = []
    for name in names:
        guid = guid_of(name)
        path = Path(out_dir) / f"{name}.fmu"
        if not force and path.exists() and is_current(path, name, guid):
            built.append(BuiltFmu(name, path, guid, rebuilt=False))
        else:
            built.append(BuiltFmu(name, build(name, guid, Path(out_dir)), guid, rebuilt=True))
    return built


def build_fmus(out_dir: Path = DEFAULT_OUT, force: bool = False, names: tuple[str, ...] = FMU_NAMES) -> list[BuiltFmu]:
    """Build FMUs ``names`` into ``out_dir`` unless an up-to-date one (same GUID) is already there."""
    return build_stale(out_dir, force, names, expected_guid, is_complete,
                       lambda name, guid, folder: _build_one(name, folder, guid))
