"""The pythonfmu builder: the slaves (fmus/slaves) as FMI 2.0 co-simulation FMUs, packaged by pythonfmu.

pythonfmu lays out the archive (its runtime binary, its Python glue, the slave script). We then
replace its model description with a complete one, add documentation/index.html and the model
package as resources, and write the archive reproducibly (sorted entries, fixed timestamps). The
GUID is derived from a digest of every bundled source, so an FMU is rebuilt exactly when a source
changes and a trace can name the model version it ran.
"""

from __future__ import annotations

import hashlib
import sys
import tempfile
import zipfile
from pathlib import Path

# Imported here, first, on purpose: our FMUs run in the host's interpreter, and if one runs before
# anything imported pythonfmu, it imports pythonfmu from the FMU's resources folder, a copy without
# the runtime binaries that the builder copies into every FMU (see _builder). It costs nothing extra:
# the FMUs' slaves import pythonfmu in every run anyway.
import pythonfmu  # noqa: F401

import fmus
from fmus.builders.base import (DEFAULT_OUT, LINK_FMU, LIVE_FMU, PACKAGE_DIR, REMOTE_FMU, ROOT, Builder, BuildError,
                                slave_instance)
from fmus.modeldescription.fmi2 import guid_for, model_description
from fmus.platforms import binary_entry

# the folders whose every module an FMU carries: a module added to one changes the GUIDs
BUNDLED_FOLDERS = (PACKAGE_DIR / "model", PACKAGE_DIR / "slaves")
# the modules (below fmus/) that shape what this builder writes: a change to one rebuilds the FMUs
BUILDER_MODULES = ("builders/base.py", "builders/pythonfmu.py", "modeldescription/core.py", "modeldescription/fmi2.py",
                   "documentation.py")
# What an FMU carries beyond fmus/model and fmus/slaves. Every one carries the fmus modules the
# Zenoh-speaking FMUs import (the component interface, its error, the pacer): FMUs in one host share
# sys.modules, and the first FMU to load ``fmus`` (a Vehicle, say) must hold what a later LiveVehicle
# or RemoteVehicle imports from it. The LiveVehicle FMU runs the bridge's host side (bridge.live and what
# it imports); the RemoteVehicle FMU runs the served-FMU client (bridge.fmu_client, bridge.fmu_wire). Both
# carry the same bridge code, for the same reason. Either needs nothing but zenoh installed.
_ONLY_IN = {"LiveVehicle.py": LIVE_FMU, "Link.py": LINK_FMU, "RemoteVehicle.py": REMOTE_FMU}
_SHARED_SOURCES = ("fmus/component.py", "fmus/errors.py", "fmus/realtime.py")
_ZENOH_SOURCES = ("bridge/__init__.py", "bridge/claim.py", "bridge/fmu_client.py", "bridge/fmu_wire.py", "bridge/lab_key.py",
                  "bridge/live.py", "bridge/protocol.py", "bridge/session.py", "bridge/motion_watch.py", "bridge/states.py",
                  "bridge/tls_probe.py")
_EXTRA_SOURCES = {LIVE_FMU: _ZENOH_SOURCES, REMOTE_FMU: _ZENOH_SOURCES}


def bundled_sources(name: str = "Vehicle") -> list[Path]:
    """The package files FMU ``name`` carries as resources (its code must need nothing else)."""
    files = [PACKAGE_DIR / "__init__.py"]
    for folder in BUNDLED_FOLDERS:
        files += sorted(path for path in folder.glob("*.py") if _ONLY_IN.get(path.name, name) == name)
    return files + [ROOT / extra for extra in _SHARED_SOURCES + _EXTRA_SOURCES.get(name, ())]


def pythonfmu_version() -> str:
    """pythonfmu's installed version, as its distribution's metadata says (part of every FMU's GUID: it
    numbers the variables). importlib.metadata is imported here, when a GUID is computed: a run whose FMUs
    were found current before does not need it (orchestrator/components/fmu_checks.py)."""
    import importlib.metadata

    return importlib.metadata.version("pythonfmu")


def digest_files(name: str = "Vehicle") -> list[Path]:
    """The files ``source_digest`` reads for FMU ``name``, in its order."""
    return bundled_sources(name) + [PACKAGE_DIR / module for module in BUILDER_MODULES]


def source_digest(name: str = "Vehicle") -> str:
    """Digest of everything that shapes FMU ``name``: bundled sources, builder modules, pythonfmu version."""
    digest = hashlib.sha256(pythonfmu_version().encode())
    for path in digest_files(name):
        digest.update(str(path.relative_to(PACKAGE_DIR) if path.is_relative_to(PACKAGE_DIR)
                          else path.relative_to(ROOT)).encode())
        digest.update(path.read_bytes())
    return digest.hexdigest()


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


class PythonFmuBuilder(Builder):
    """FMI 2.0 FMUs whose binary is pythonfmu's runtime, running the model's Python in the host's libpython."""

    kind = "python"
    fmi_version = 2
    default_out = DEFAULT_OUT

    def expected_guid(self, name: str) -> str:
        return guid_for(source_digest(name), name)

    def digest_files(self, name: str) -> list[Path]:
        return digest_files(name)

    def required_entries(self, name: str) -> set[str]:
        """The binary for this platform, the slave script and every bundled source."""
        required = {binary_entry(name, 2), f"resources/{name}.py"}
        return required | {f"resources/{source.relative_to(ROOT).as_posix()}" for source in bundled_sources(name)}

    def build_one(self, name: str, guid: str) -> dict[str, bytes]:
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
            slave = slave_instance(name)
            entries: dict[str, bytes] = {}
            with zipfile.ZipFile(raw) as archive:
                for item in archive.infolist():
                    if item.filename != "modelDescription.xml" and not item.is_dir():
                        entries[item.filename] = archive.read(item)
        if not any(entry.startswith("binaries/") for entry in entries):
            raise BuildError(f"{name}.fmu: pythonfmu's builder produced no binaries; the FMU was not written")
        for path in bundled_sources(name):
            entries[f"resources/{path.relative_to(ROOT).as_posix()}"] = path.read_bytes()
        entries["modelDescription.xml"] = model_description(slave, guid, version)
        entries["documentation/index.html"] = documentation_html(slave, version).encode()
        return entries
