"""Where an FMU keeps the binary for a platform: the one place that names FMI's binaries folders.

FMI 2.0 names a folder by operating system and word size (``linux64``, ``win64``, ``darwin64``; section
2.3, "binaries"); FMI 3.0 by a platform tuple ``<architecture>-<operating system>`` (``x86_64-linux``,
``aarch64-darwin``; section 2.5.1.1, "Platform Tuple Definition"). A ``Platform`` gives both, and the
shared-library suffix, so the builders, the completeness checks and the tests all ask this module.
``host_platform()`` is this machine as FMPy sees it (FMPy's ``platform``, ``platform_tuple`` and
``sharedLibraryExtension``; tests/test_startup.py compares them), without importing FMPy, which a run of
the native engine does not need (~0.04 s of start-up).
"""

from __future__ import annotations

import platform as _host
import sys
from dataclasses import dataclass

_SUFFIX = {"linux": ".so", "windows": ".dll", "darwin": ".dylib"}
_FMI2_SYSTEM = {"linux": "linux", "windows": "win", "darwin": "darwin"}


@dataclass(frozen=True)
class Platform:
    """An operating system and architecture an FMU binary runs on, in FMI 3.0's words."""

    architecture: str  # "x86_64", "aarch64" or "x86"
    system: str  # "linux", "windows" or "darwin"

    @property
    def suffix(self) -> str:
        """The shared library's file-name suffix: ".so", ".dll", ".dylib"."""
        return _SUFFIX.get(self.system, "")

    @property
    def tuple(self) -> str:
        """The FMI 3.0 platform tuple, e.g. "aarch64-linux"."""
        return f"{self.architecture}-{self.system}"

    def directory(self, fmi_version: int) -> str:
        """The folder below binaries/ for this platform in an FMI ``fmi_version`` (2 or 3) FMU. FMI 2.0
        names no architecture: "darwin64" holds one binary for both Mac architectures (a universal one)."""
        if fmi_version == 3:
            return self.tuple
        return _FMI2_SYSTEM.get(self.system, self.system) + ("32" if self.architecture == "x86" else "64")


# What `platoon build --all-platforms` builds for: where importers (Simulink, Dymola, OMSimulator, FMPy,
# libcosim) run, and robot computers (aarch64 Linux).
RELEASE_PLATFORMS = (Platform("x86_64", "linux"), Platform("aarch64", "linux"), Platform("x86_64", "windows"),
                     Platform("x86_64", "darwin"), Platform("aarch64", "darwin"))


def release_layout(fmi_version: int) -> dict[str, tuple[Platform, ...]]:
    """The binaries/ folders of a release FMU of FMI ``fmi_version``, each with the platforms its binary
    is built for. FMI 3.0: one folder per platform tuple. FMI 2.0: linux64, win64, and darwin64 with one
    universal binary for both Mac architectures (FMPy and other FMI 2.0 importers load darwin64 on either);
    FMI 2.0 has no folder for aarch64 Linux (FMPy would look for it in linux64, the x86_64 binary's), so
    there the FMI 3.0 FMU or the sources serve."""
    if fmi_version == 3:
        return {platform.tuple: (platform,) for platform in RELEASE_PLATFORMS}
    layout: dict[str, tuple[Platform, ...]] = {}
    for platform in RELEASE_PLATFORMS:
        if platform != Platform("aarch64", "linux"):
            layout[platform.directory(2)] = layout.get(platform.directory(2), ()) + (platform,)
    return layout


def host_platform() -> Platform:
    """This machine, named as FMPy names it."""
    system = next((name for prefix, name in (("win", "windows"), ("linux", "linux"), ("darwin", "darwin"))
                   if sys.platform.startswith(prefix)), sys.platform)
    machine = _host.machine().lower()
    if machine in {"aarch64", "arm64"}:
        return Platform("aarch64", system)
    return Platform("x86_64" if sys.maxsize > 2**32 else "x86", system)


def binary_entry(model_identifier: str, fmi_version: int, platform: Platform | None = None) -> str:
    """The archive entry of ``model_identifier``'s binary for ``platform`` (default: this machine)."""
    platform = platform or host_platform()
    return f"binaries/{platform.directory(fmi_version)}/{model_identifier}{platform.suffix}"


def fmi_platform() -> tuple[str, str]:
    """This machine's FMI 2.0 binaries folder and shared-library suffix, e.g. ("linux64", ".so")."""
    host = host_platform()
    return host.directory(2), host.suffix
