"""The C toolchain of the native FMUs: which compiler, with which flags and FMI headers, compiles them.

A binary for this machine is built with the system C compiler (``$CC`` or ``cc``); binaries for other
platforms (``platoon build --all-platforms``: ``fmus.platforms.RELEASE_PLATFORMS``) with Zig's clang
(``python -m ziglang cc -target ...``, the optional ``release`` extra), which brings the C library
headers and link stubs of Linux (glibc), Windows (MinGW-w64) and macOS, so no SDK is downloaded. Both
use FMI's own headers from FMPy's copy (``fmpy/c-code``) and compile in a scratch folder holding copies
of the sources and the generated headers. The flags that make the numbers Python's (``CFLAGS``:
``-ffp-contract=off``) are the same for every target.
"""

from __future__ import annotations

import os
import shutil
import signal
import struct
import subprocess
import sys
import time
from pathlib import Path
from typing import Callable

from fmus.builders.base import PACKAGE_DIR, BuildError
from fmus.platforms import Platform

NATIVE_SOURCES = PACKAGE_DIR / "native"
HEADERS = ("framework.h", "pymath.h", "science.h")
FMI_HEADERS = {2: ("fmi2Functions.h", "fmi2FunctionTypes.h", "fmi2TypesPlatform.h"),
               3: ("fmi3Functions.h", "fmi3FunctionTypes.h", "fmi3PlatformTypes.h")}
# -ffp-contract=off: no fused multiply-add, so every rounding is the one Python makes (fmus/native/pymath.h);
# -fvisibility=hidden: only the fmi2* functions (FMI2_Export in FMI's header) leave the binary.
CFLAGS = ("-std=c99", "-O2", "-fPIC", "-shared", "-ffp-contract=off", "-fvisibility=hidden", "-Wall", "-Wextra")
LIBS = ("-lm",)
# Zig's target triple of each release platform, with the oldest C library it is built against: glibc
# 2.17 (manylinux2014's baseline: the binary runs on any Linux since 2012; the system compiler's would
# need this machine's glibc), macOS 10.13 on Intel and 11.0 (the first) on Apple silicon.
ZIG_TARGETS = {
    Platform("x86_64", "linux"): "x86_64-linux-gnu.2.17",
    Platform("aarch64", "linux"): "aarch64-linux-gnu.2.17",
    Platform("x86_64", "windows"): "x86_64-windows-gnu",
    Platform("x86_64", "darwin"): "x86_64-macos.10.13",
    Platform("aarch64", "darwin"): "aarch64-macos.11.0",
}


# s: how long one compiler process may take before it is stopped (PLATOON_COMPILE_TIMEOUT). A compile of
# our FMU takes a second or two; a first Zig compile for a target also builds that target's C runtime into
# Zig's cache: 135 s for Windows with a cold cache at load 5-8 (docs/fmus.md, "Cost"), 2-3x that on a busier
# machine. The limit only stops a compiler that hangs; a slow cold cache reaching it gets CompileTimeout's
# advice (run again with a longer limit: the cache keeps the targets Zig finished).
COMPILE_TIMEOUT_VARIABLE = "PLATOON_COMPILE_TIMEOUT"
DEFAULT_COMPILE_TIMEOUT = 600.0
# s: warming Zig's cache (fmus/builders/zig_cache.py) is the first compile for a target by design: Windows'
# C runtime took 135 s at load 5-8 and 765 s at load about 20 (2026-12-02); the same variable sets it.
DEFAULT_WARM_TIMEOUT = 1800.0
WARM_ADVICE = "or warm Zig's cache first: python -m fmus.builders.zig_cache"


class CompileTimeout(BuildError):
    """A compiler process ran past ``compile_timeout()`` and was stopped (with every process it started)."""


class NoCompiler(BuildError):
    """No C compiler on this machine: the native FMUs cannot be built (the pythonfmu ones still can)."""


class NoCrossCompiler(BuildError):
    """Zig's toolchain (the ziglang package) is not installed: no binaries for other platforms (asked for
    explicitly, so a failure, where a missing system compiler only skips the native FMUs)."""


def compiler() -> str:
    """The C compiler to use: $CC, else cc, gcc or clang on PATH."""
    for candidate in (os.environ.get("CC"), "cc", "gcc", "clang"):
        if candidate and shutil.which(candidate):
            return shutil.which(candidate)  # type: ignore[return-value]
    raise NoCompiler("no C compiler found ($CC, cc, gcc or clang): the native FMUs were not built "
                     "(the pythonfmu FMUs do not need one)")


def fmi_headers() -> Path:
    """The folder of FMI's standard C headers that FMPy ships (fmi2Functions.h, fmi3Functions.h, ...);
    found without importing FMPy, which a run of the native engine does not need (~0.04 s)."""
    from importlib.util import find_spec

    spec = find_spec("fmpy")
    if spec is None or spec.origin is None:
        raise BuildError("FMPy is not installed: its FMI headers are needed to build the native FMUs")
    return Path(spec.origin).resolve().parent / "c-code"


def zig_cc() -> list[str]:
    """The command of Zig's C compiler, from the ziglang package in this Python."""
    from importlib.util import find_spec

    if find_spec("ziglang") is None:
        raise NoCrossCompiler("binaries for other platforms need Zig's toolchain: pip install 'platoon-cosim[release]' "
                              "(the ziglang package)")
    return [sys.executable, "-m", "ziglang", "cc"]


def compile_timeout(default: float = DEFAULT_COMPILE_TIMEOUT) -> float:
    """The seconds one compiler process may take (``PLATOON_COMPILE_TIMEOUT``, > 0; else ``default``)."""
    try:
        value = float(os.environ.get(COMPILE_TIMEOUT_VARIABLE, ""))
    except ValueError:
        return default
    return value if 0 < value < float("inf") else default


def zig_timeout_text(target: str, limit: float) -> str:
    """One line for a Zig compile for ``target`` stopped after ``limit`` s: what was most likely going on, and
    what to do."""
    return (f"Zig's compiler for {target} did not finish within {limit:.0f} s: Zig was most likely still building "
            f"its C runtime for {target} (the first build for a target: minutes on a busy machine; nothing "
            f"half-built was kept). Run the same command again, with {COMPILE_TIMEOUT_VARIABLE}=SECONDS to give it "
            f"longer (Zig's cache keeps the targets it finished, but builds a C runtime whole: Windows' took 765 s at "
            f"load 20), {WARM_ADVICE}")


def run_compiler(command: list[str], cwd: Path, timeout_text: Callable[[float], str],
                 waiting: Callable[[float], None] | None = None, every: float = 5.0,
                 limit: float | None = None) -> subprocess.CompletedProcess:
    """Run a compiler ``command`` in ``cwd``, its output captured; ``waiting(seconds so far)`` after ``every`` s
    while it runs, then each time the time so far has doubled (a first Zig compile takes minutes: the caller
    shows it is alive, in a few lines, not a screenful). Past
    ``limit`` (default ``compile_timeout()``) the compiler is stopped and ``CompileTimeout(timeout_text(limit))``
    raised. The
    compiler runs in a process group of its own, stopped as a whole (``python -m ziglang cc`` starts zig,
    which starts clang), on a timeout and on Ctrl-C alike: no compiler is left writing to Zig's cache."""
    limit = compile_timeout() if limit is None else limit
    process = subprocess.Popen(command, cwd=cwd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                               start_new_session=True)
    started = time.monotonic()
    next_word = every
    try:
        while True:
            so_far = time.monotonic() - started
            try:
                stdout, stderr = process.communicate(timeout=max(0.01, min(next_word, limit) - so_far))
                return subprocess.CompletedProcess(command, process.returncode, stdout, stderr)
            except subprocess.TimeoutExpired:
                so_far = time.monotonic() - started
                if so_far >= limit:
                    raise CompileTimeout(timeout_text(limit)) from None
                if so_far >= next_word:
                    next_word = max(every, 2 * so_far)
                    if waiting is not None:
                        waiting(so_far)
    finally:
        if process.poll() is None:
            _stop_group(process)


def _stop_group(process: subprocess.Popen) -> None:
    """Kill ``process`` and every process of its group, and reap it."""
    try:
        os.killpg(process.pid, signal.SIGKILL)
    except ProcessLookupError:
        pass
    process.communicate()


def cross_flags(name: str, platform: Platform) -> list[str]:
    """Zig's flags for ``platform``: its target, CFLAGS (no -fPIC on Windows, where every DLL is
    relocatable and clang refuses the flag), no debug information or symbol table (they would hold the
    scratch folder's path: the binary would differ from build to build), and on macOS an install name
    that holds no path either."""
    flags = ["-target", ZIG_TARGETS[platform], *(flag for flag in CFLAGS if not (flag == "-fPIC" and
                                                                             platform.system == "windows"))]
    flags += ["-g0", "-s"]
    if platform.system == "darwin":
        flags.append(f"-Wl,-install_name,@rpath/{name}{platform.suffix}")
    return flags


def compile_binary(name: str, files: tuple[str, ...], generated: dict[str, str], scratch: Path,
                   target: Platform | None = None, waiting: Callable[[float], None] | None = None) -> bytes:
    """The shared library of FMU ``name``, compiled in ``scratch`` from copies of the C ``files`` and
    HEADERS (fmus/native) with the ``generated`` headers (name: text): for this machine with the system
    compiler, or for ``target`` with Zig's (``waiting``: as ``run_compiler``'s)."""
    sources = scratch / "sources"
    sources.mkdir(parents=True)
    for file in files + HEADERS:
        shutil.copyfile(NATIVE_SOURCES / file, sources / file)
    for file, text in generated.items():
        (sources / file).write_text(text)
    if target is None:
        output, compile_command = scratch / f"{name}.so", [compiler(), *CFLAGS]
    else:
        output, compile_command = scratch / f"{name}{target.suffix}", [*zig_cc(), *cross_flags(name, target)]
    command = [*compile_command, f"-I{fmi_headers()}", "-I.", *files, "-o", str(output), *LIBS]
    if target is None:
        def timeout_text(limit: float) -> str:
            return f"{name}: the C compiler ({command[0]}) did not finish within {limit:.0f} s"
    else:
        def timeout_text(limit: float) -> str:
            return f"{name}: {zig_timeout_text(ZIG_TARGETS[target], limit)}"
    result = run_compiler(command, sources, timeout_text, waiting)
    if result.returncode != 0:
        raise BuildError(f"{name}: compiling the native FMU failed ({' '.join(command)}):\n{result.stderr.strip()}")
    return output.read_bytes()


def universal_binary(slices: list[bytes]) -> bytes:
    """One Mach-O "fat" file holding the thin ``slices`` (what Apple's lipo writes), for FMI 2.0's single
    darwin64 folder. Header and slice table are big-endian (mach-o/fat.h: FAT_MAGIC, then per slice the
    CPU type and subtype, copied from the slice's own header, offset, size and alignment); each slice
    starts at a multiple of 2^14 bytes, the page size of Apple silicon."""
    align = 14
    table_end = 8 + 20 * len(slices)
    entries, body, offset = [], b"", 0
    for thin in slices:
        if thin[:4] != b"\xcf\xfa\xed\xfe":  # MH_MAGIC_64, little-endian: both our architectures
            raise BuildError("universal_binary: a slice is not a 64-bit little-endian Mach-O file")
        cpu_type, cpu_subtype = struct.unpack_from("<Ii", thin, 4)
        offset = -(-(table_end + len(body)) // (1 << align)) << align
        body += b"\0" * (offset - table_end - len(body)) + thin
        entries.append(struct.pack(">IiIII", cpu_type, cpu_subtype, offset, len(thin), align))
    return struct.pack(">II", 0xCAFEBABE, len(slices)) + b"".join(entries) + body
