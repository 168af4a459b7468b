"""Native FMUs for every platform an importer runs on: `platoon build --all-platforms`.

The release FMUs carry binaries for x86_64 and aarch64 Linux, x86_64 Windows and x86_64 and aarch64
macOS, cross-compiled on this Linux machine with Zig (``ziglang``). They are run, not just built:

* the aarch64 Linux binary under qemu-user, in ``tests/c_host/minimal_host3.c`` compiled for aarch64,
  against the aarch64 glibc of Debian's ``libc6-arm64-cross``;
* the Windows DLLs under wine, in ``minimal_host.c`` and ``minimal_host3.c`` compiled for Windows;

and their CSV is compared with the same hosts running this machine's binary (x86_64 Linux, built by the
system compiler as a plain `platoon build` does). macOS binaries cannot run here: their Mach-O format,
architectures, exports and libraries are read with LIEF. Without ziglang, qemu-user or wine the tests
that need them are skipped, saying which is missing and how to install it.
"""

from __future__ import annotations

import platform
import re
import shutil
import subprocess
import sys
import zipfile
from importlib.util import find_spec
from pathlib import Path

import fmpy
import numpy as np
import pytest
from fmpy.validation import validate_fmu

from fmus.builders import DEFAULT_OUT, FMU_NAMES, NativeBuilder
from fmus.builders.toolchain import fmi_headers
from fmus.platforms import release_layout
from tests.conftest import shared_build

REPO = Path(__file__).resolve().parents[1]
HOSTS = Path(__file__).resolve().parent / "c_host"
HOST_SOURCE = {2: HOSTS / "minimal_host.c", 3: HOSTS / "minimal_host3.c"}
OUTPUTS = {"Vehicle": ("x", "y", "speed", "gap"), "VirtualTarget": ("x", "y", "speed", "arc_length")}
AARCH64_SYSROOT = Path("/usr/aarch64-linux-gnu")  # Debian's libc6-arm64-cross: aarch64 glibc for qemu-user
TIMEOUT = 600
# The Windows binaries take sin, cos and log from MinGW-w64's runtime and atan2 from the UCRT, not from
# glibc: those differ from glibc's in the last bit for some arguments (docs/fmus.md, "Every platform"),
# so the Windows trajectories are not bit-identical to Linux's. Over the 60 s default experiment the
# difference stayed below 3e-13 m (measured under wine 8.0); 1e-9 is the C host's tolerance against
# FMPy (tests/test_c_host.py), far below anything the platoon's metrics resolve.
WINDOWS_TOLERANCE = 1e-9
# the dylib's own header and the DSO handle: defined (and exported) by Zig's linker in every dylib; no
# FMI name, so no importer looks them up
MACHO_LINKER_SYMBOLS = {"_mh_dylib_header", "__dso_handle"}

# slow: cross-compiling five binaries and running them under wine and qemu takes minutes (pytest -m slow;
# CI runs it); the native FMUs this machine builds are tested in the default run (tests/test_native_fmus.py)
pytestmark = [pytest.mark.skipif(sys.platform != "linux" or platform.machine() != "x86_64",
                                 reason="the reference run is this machine's x86_64 Linux binary"),
              pytest.mark.slow]


def _zig() -> list[str]:
    if find_spec("ziglang") is None:
        pytest.skip("ziglang is not installed (pip install -e '.[release]'): no cross-compiled binaries")
    return [sys.executable, "-m", "ziglang", "cc"]


@pytest.fixture(scope="module")
def release(tmp_path_factory, zig_cache) -> dict[int, dict[str, Path]]:
    """`platoon build --all-platforms` into a fresh folder: the native FMUs by FMI version and name
    (Zig's cache warmed first, once per machine: tests/conftest.py)."""
    _zig()
    out = tmp_path_factory.mktemp("release")
    command = [sys.executable, "-c", "import sys; sys.argv[0] = 'platoon'; from orchestrator.cli import main; main()",
               "build", "--all-platforms", "--out", str(out)]
    result = subprocess.run(command, capture_output=True, text=True, cwd=REPO, timeout=TIMEOUT)
    assert result.returncode == 0, result.stdout + result.stderr
    return {2: {name: out / "native" / f"{name}.fmu" for name in FMU_NAMES},
            3: {name: out / "fmi3" / f"{name}.fmu" for name in FMU_NAMES}}


@pytest.fixture(scope="module")
def host_build() -> dict[int, dict[str, Path]]:
    """The FMUs a plain `platoon build` makes (this machine's binary, the system compiler)."""
    with shared_build():
        return {version: {fmu.name: fmu.path for fmu in NativeBuilder(version).build(REPO / DEFAULT_OUT / folder)}
                for version, folder in ((2, "native"), (3, "fmi3"))}


def _exports(binary) -> set[str]:
    """The functions a shared library exports, without Mach-O's leading underscore."""
    import lief

    if isinstance(binary, lief.PE.Binary):
        return {entry.name for entry in binary.get_export().entries}
    names = {symbol.name for symbol in binary.exported_symbols}
    if isinstance(binary, lief.MachO.Binary):  # Zig's Mach-O linker also exports the two symbols it defines
        return {name[1:] for name in names} - MACHO_LINKER_SYMBOLS
    return names


def _parse(data: bytes):
    import lief

    lief.logging.disable()
    return lief.parse(list(data)) if data[:4] != b"\xca\xfe\xba\xbe" else lief.MachO.parse(list(data))


@pytest.mark.parametrize("version", (2, 3))
def test_a_release_fmu_carries_every_platform_with_the_host_builds_guid_and_exports(release, host_build, version):
    import lief

    for name in FMU_NAMES:
        with zipfile.ZipFile(release[version][name]) as archive:
            binaries = {entry: archive.read(entry) for entry in archive.namelist() if entry.startswith("binaries/")}
        with zipfile.ZipFile(host_build[version][name]) as archive:
            host_binary = next(archive.read(entry) for entry in archive.namelist() if entry.startswith("binaries/"))
        expected = {f"binaries/{folder}/{name}{platforms[0].suffix}" for folder, platforms in
                    release_layout(version).items()}
        assert set(binaries) == expected
        assert fmpy.read_model_description(str(release[version][name])).guid == NativeBuilder(version).expected_guid(name)
        fmi_functions = _exports(_parse(host_binary))
        assert fmi_functions and fmi_functions <= _standard_functions(version)  # the tested binary's exports
        for entry, data in binaries.items():
            folder = entry.split("/")[1]
            binary = _parse(data)
            slices = list(binary) if isinstance(binary, lief.MachO.FatBinary) else [binary]
            assert [_architecture(thin) for thin in slices] == [p.architecture for p in release_layout(version)[folder]]
            for thin in slices:
                assert _exports(thin) == fmi_functions, entry  # the FMI functions, nothing else
                _check_format(thin, release_layout(version)[folder][0].system, entry)


def _standard_functions(version: int) -> set[str]:
    """Every function FMI ``version``'s fmiXFunctions.h declares (FMIX_Export fmiXNameTYPE fmiXName;)."""
    header = (fmi_headers() / f"fmi{version}Functions.h").read_text()
    return set(re.findall(rf"FMI{version}_Export\s+fmi{version}\w+TYPE\s+(fmi{version}\w+);", header))


def _architecture(binary) -> str:
    import lief

    if isinstance(binary, lief.ELF.Binary):
        return {lief.ELF.ARCH.X86_64: "x86_64", lief.ELF.ARCH.AARCH64: "aarch64"}[binary.header.machine_type]
    if isinstance(binary, lief.PE.Binary):
        return {lief.PE.Header.MACHINE_TYPES.AMD64: "x86_64"}[binary.header.machine]
    return {lief.MachO.Header.CPU_TYPE.X86_64: "x86_64", lief.MachO.Header.CPU_TYPE.ARM64: "aarch64"}[
        binary.header.cpu_type]


def _check_format(binary, system: str, entry: str) -> None:
    """A shared library of ``system``'s format that needs only the C library (and glibc no newer than 2.17)."""
    import lief

    if system == "linux":
        assert isinstance(binary, lief.ELF.Binary) and binary.header.file_type == lief.ELF.Header.FILE_TYPE.DYN
        versions = {symbol.symbol_version.symbol_version_auxiliary.name for symbol in binary.imported_symbols
                    if symbol.has_version and symbol.symbol_version.has_auxiliary_version}
        glibc = [tuple(map(int, v.removeprefix("GLIBC_").split("."))) for v in versions if v.startswith("GLIBC_")]
        assert glibc and max(glibc) <= (2, 17), (entry, sorted(versions))
        assert set(binary.libraries) <= {"libc.so.6", "libm.so.6"}, (entry, binary.libraries)
    elif system == "windows":
        assert isinstance(binary, lief.PE.Binary) and binary.header.has_characteristic(
            lief.PE.Header.CHARACTERISTICS.DLL)
        assert {library.lower() for library in binary.libraries} <= {"kernel32.dll"} | {
            library.lower() for library in binary.libraries if library.lower().startswith("api-ms-win-crt-")}, entry
    else:
        assert isinstance(binary, lief.MachO.Binary) and binary.header.file_type == lief.MachO.Header.FILE_TYPE.DYLIB
        assert [library.name for library in binary.libraries][1:] == ["/usr/lib/libSystem.B.dylib"], entry


def test_a_release_fmu_counts_as_built_for_this_machine_and_a_host_build_not_as_a_release(release, host_build):
    """`platoon build` after `--all-platforms` keeps the release FMUs; `--all-platforms` after a plain
    build rebuilds (the host build lacks the other platforms' binaries)."""
    for version in (2, 3):
        for name in FMU_NAMES:
            guid = NativeBuilder(version).expected_guid(name)
            assert NativeBuilder(version).is_complete(release[version][name], name, guid)
            assert not NativeBuilder(version, all_platforms=True).is_complete(host_build[version][name], name, guid)


@pytest.mark.parametrize("version", (2, 3))
def test_fmpy_validates_the_release_fmus_and_runs_them_as_the_host_build(release, host_build, version):
    for name in FMU_NAMES:
        assert validate_fmu(str(release[version][name])) == []
        runs = [fmpy.simulate_fmu(str(fmu), stop_time=2.0, output=list(OUTPUTS[name]))
                for fmu in (release[version][name], host_build[version][name])]
        assert len(runs[0]) == len(runs[1]) > 100
        assert all(np.array_equal(runs[0][output], runs[1][output]) for output in OUTPUTS[name]), name


# --- running the binaries: this machine, aarch64 Linux under qemu-user, Windows under wine ---------------

def _compile_host(version: int, target: str | None, out: Path) -> Path:
    """minimal_host(3).c for this machine (system compiler) or Zig's ``target``."""
    flags = ["-std=c99", "-Wall", "-Wextra", "-Werror", "-O2", f"-I{fmi_headers()}", "-o", str(out),
             str(HOST_SOURCE[version])]
    if target is None:
        command = [shutil.which("cc") or "cc", *flags, "-ldl"]
    elif "windows" in target:  # MinGW's own printf: %.17g exact whatever the C runtime's printf does
        command = [*_zig(), "-target", target, "-D__USE_MINGW_ANSI_STDIO=1", *flags]
    else:
        command = [*_zig(), "-target", target, *flags, "-ldl"]
    result = subprocess.run(command, capture_output=True, text=True, timeout=TIMEOUT)
    assert result.returncode == 0, f"compiling {HOST_SOURCE[version].name} for {target or 'this machine'} failed:\n{result.stderr}"
    return out


def _run(prefix: list[str], host: Path, fmu: Path, folder: Path, name: str, env: dict[str, str],
         windows: bool = False) -> list[list[float]]:
    """The C host over ``fmu``'s default experiment (unzipped into ``folder``): its rows of numbers."""
    with zipfile.ZipFile(fmu) as archive:
        archive.extractall(folder)
    md = fmpy.read_model_description(str(fmu))
    refs = {v.name: v.valueReference for v in md.modelVariables}
    step = float(md.defaultExperiment.stepSize)
    steps = round(float(md.defaultExperiment.stopTime) / step)
    where = f"Z:{folder}" if windows else str(folder)  # wine's drive Z: is the root of the Linux file system
    args = [*prefix, str(host), where, md.guid, str(steps), repr(step), *(str(refs[o]) for o in OUTPUTS[name]), name]
    result = subprocess.run(args, capture_output=True, text=True, env=env, timeout=TIMEOUT)
    assert result.returncode == 0, f"{' '.join(args)} failed ({result.returncode}):\n{result.stderr}"
    lines = result.stdout.replace("\r\n", "\n").splitlines()
    assert lines[0] == "t,x,y,speed,gap" and len(lines) == steps + 2
    return [[float(value) for value in line.split(",")] for line in lines[1:]]


@pytest.fixture(scope="module")
def reference(host_build, tmp_path_factory) -> dict[tuple[int, str], list[list[float]]]:
    """The x86_64 Linux runs: this machine's C hosts on the plain build's FMUs."""
    folder = tmp_path_factory.mktemp("x86_64")
    hosts = {version: _compile_host(version, None, folder / f"host{version}") for version in (2, 3)}
    return {(version, name): _run([], hosts[version], host_build[version][name], folder / f"{version}{name}", name, {})
            for version in (2, 3) for name in FMU_NAMES}


def test_the_release_x86_64_linux_binaries_give_the_host_builds_numbers(release, reference, tmp_path):
    """Zig's x86_64 Linux binary (glibc 2.17 baseline) against the system compiler's: the same bits."""
    hosts = {version: _compile_host(version, None, tmp_path / f"host{version}") for version in (2, 3)}
    for version in (2, 3):
        for name in FMU_NAMES:
            rows = _run([], hosts[version], release[version][name], tmp_path / f"{version}{name}", name, {})
            assert rows == reference[(version, name)], (version, name)


def test_the_aarch64_linux_binary_under_qemu_gives_the_x86_64_numbers(release, reference, tmp_path):
    """FMI 3.0 (FMI 2.0 names no aarch64 Linux folder): bit-identical, glibc's libm gives aarch64 the same
    results as x86_64 for the functions the model calls."""
    qemu = shutil.which("qemu-aarch64")
    if qemu is None or not (AARCH64_SYSROOT / "lib" / "ld-linux-aarch64.so.1").exists():
        pytest.skip("qemu-user and the aarch64 glibc are not installed "
                    "(apt-get install --no-install-recommends qemu-user libc6-arm64-cross; .ci/run does)")
    host = _compile_host(3, "aarch64-linux-gnu.2.17", tmp_path / "host3-aarch64")
    for name in FMU_NAMES:
        rows = _run([qemu, "-L", str(AARCH64_SYSROOT)], host, release[3][name], tmp_path / name, name, {})
        assert rows == reference[(3, name)], name


@pytest.fixture(scope="module")
def wine(tmp_path_factory) -> tuple[str, dict[str, str]]:
    """wine, and the environment of a prefix of its own (made on first use, ~8 s), with no Mono or Gecko
    installer and no wine debug output."""
    found = shutil.which("wine") or shutil.which("wine64") or next(
        (str(path) for path in (Path("/usr/lib/wine/wine64"),) if path.exists()), None)
    if found is None:
        pytest.skip("wine is not installed (apt-get install --no-install-recommends wine64; .ci/run does)")
    folder = tmp_path_factory.mktemp("wine")
    return found, {"PATH": "/usr/bin:/bin", "HOME": str(folder), "WINEPREFIX": str(folder / "prefix"),
                   "WINEDEBUG": "-all", "WINEDLLOVERRIDES": "mscoree,mshtml="}


@pytest.mark.parametrize("version", (2, 3))
def test_the_windows_dlls_under_wine_give_the_x86_64_numbers_to_1e_9(release, reference, wine, version, tmp_path):
    """Not bit-identical (see WINDOWS_TOLERANCE): same steps and times, outputs within 1e-9."""
    host = _compile_host(version, "x86_64-windows-gnu", tmp_path / f"host{version}.exe")
    for name in FMU_NAMES:
        rows = _run([wine[0]], host, release[version][name], tmp_path / name, name, wine[1], windows=True)
        expected = reference[(version, name)]
        assert [row[0] for row in rows] == [row[0] for row in expected]
        worst = max(abs(a - b) for row, other in zip(rows, expected) for a, b in zip(row[1:], other[1:]))
        assert worst <= WINDOWS_TOLERANCE, f"{name}: Windows and Linux differ by {worst:g}"
