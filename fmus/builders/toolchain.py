"""The C toolchain of the native FMUs: which compiler, with which flags and FMI headers, compiles them.

The binary is built with the system C compiler (``$CC`` or ``cc``) and FMI's own headers from FMPy's
copy (``fmpy/c-code``), in a scratch folder holding copies of the sources and the generated headers.
"""

from __future__ import annotations

import os
import shutil
import subprocess
from pathlib import Path

from fmus.builders.base import PACKAGE_DIR, BuildError

NATIVE_SOURCES = PACKAGE_DIR / "native"
HEADERS = ("framework.h", "pymath.h", "science.h")
FMI_HEADERS = {2: ("fmi2Functions.h", "fmi2FunctionTypes.h", "fmi2TypesPlatform.h"),
               3: ("fmi3Functions.h", "fmi3FunctionTypes.h", "fmi3PlatformTypes.h")}
# -ffp-contract=off: no fused multiply-add, so every rounding is the one Python makes (fmus/native/pymath.h);
# -fvisibility=hidden: only the fmi2* functions (FMI2_Export in FMI's header) leave the binary.
CFLAGS = ("-std=c99", "-O2", "-fPIC", "-shared", "-ffp-contract=off", "-fvisibility=hidden", "-Wall", "-Wextra")
LIBS = ("-lm",)


class NoCompiler(BuildError):
    """No C compiler on this machine: the native FMUs cannot be built (the pythonfmu ones still can)."""


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


def compile_binary(name: str, files: tuple[str, ...], generated: dict[str, str], cc: str, scratch: Path) -> bytes:
    """The shared library of FMU ``name``, compiled in ``scratch`` from copies of the C ``files`` and
    HEADERS (fmus/native) with the ``generated`` headers (name: text)."""
    sources = scratch / "sources"
    sources.mkdir()
    for file in files + HEADERS:
        shutil.copyfile(NATIVE_SOURCES / file, sources / file)
    for file, text in generated.items():
        (sources / file).write_text(text)
    output = scratch / f"{name}.so"
    command = [cc, *CFLAGS, f"-I{fmi_headers()}", "-I.", *files, "-o", str(output), *LIBS]
    result = subprocess.run(command, cwd=sources, capture_output=True, text=True, timeout=600)
    if result.returncode != 0:
        raise BuildError(f"{name}: compiling the native FMU failed ({' '.join(command)}):\n{result.stderr.strip()}")
    return output.read_bytes()
