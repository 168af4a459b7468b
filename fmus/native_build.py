"""`platoon build`, native part: the Vehicle and VirtualTarget FMUs compiled from C (fmus/native/).

The pythonfmu FMUs need a Python installation on the host; these twins need nothing but the C
library. Their C files mirror fmus/model equation by equation; what they share with the pythonfmu
FMUs is taken from the same Python declarations at build time, so nothing is written twice:

* ``variables.h`` (generated into the build): every variable's value reference (the one pythonfmu
  gives it), name, type, causality and start value, and the build's GUID;
* ``modelDescription.xml``: ``fmus.modeldescription.model_description`` of the same slave
  declarations, with the native capability flags (needsExecutionTool="false": the binary runs the
  model itself) and the C files listed as sources;
* ``documentation/index.html``: ``fmus.documentation``, with the native host requirements.

The binary is built with the system C compiler (``$CC`` or ``cc``) and FMI's own headers from FMPy's
copy (``fmpy/c-code``). The FMU also carries the C sources and the generated header (``sources/``),
so it can be compiled for another platform with one compiler command (docs/fmus.md). The GUID is a
digest of everything that shapes the FMU (C sources, the Python declarations behind the generated
header and model description, builder, compiler flags, FMI headers: ``_digest``), so an FMU is rebuilt
exactly when one of them changes; the archive
is written aside and moved into place (``fmus.build.write_fmu``), reproducibly.
"""

from __future__ import annotations

import hashlib
import importlib.metadata
import json
import os
import shutil
import subprocess
import tempfile
import zipfile
from pathlib import Path
from xml.etree import ElementTree

import fmus
from fmus.build import (DEFAULT_OUT, FMU_NAMES, PACKAGE_DIR, BuildError, BuiltFmu, _slave_instance,
                        archive_is_whole, build_stale, bundled_sources, fmi_platform, write_fmu)
from fmus.modeldescription import CAPABILITIES, guid_for

NATIVE_SOURCES = PACKAGE_DIR / "native"
NATIVE_OUT = DEFAULT_OUT / "native"
MODEL_SOURCE = {"Vehicle": "vehicle.c", "VirtualTarget": "target.c"}
COMMON_SOURCES = ("framework.c", "fmi2.c")
HEADERS = ("framework.h", "pymath.h", "science.h")
GENERATED_HEADER = "variables.h"
FMI_HEADERS = ("fmi2Functions.h", "fmi2FunctionTypes.h", "fmi2TypesPlatform.h")
# -ffp-contract=off: no fused multiply-add, so every rounding is the one Python makes (fmus/native/pymath.h);
# -fvisibility=hidden: only the fmi2* functions (FMI2_Export in FMI's header) leave the binary.
CFLAGS = ("-std=c99", "-O2", "-fPIC", "-shared", "-ffp-contract=off", "-fvisibility=hidden", "-Wall", "-Wextra")
LIBS = ("-lm",)

CAPABILITIES_NATIVE = CAPABILITIES | {"needsExecutionTool": "false"}
RUNTIME = "native C"

NATIVE_HOST = """<p>A native FMU: its binary is compiled C (this FMU's <code>sources/</code>) and needs nothing on the
host but the C library and its math library: no Python, no environment variables. To build it for another platform:
<code>cc -std=c99 -O2 -fPIC -shared -ffp-contract=off -I&lt;FMI 2.0 headers&gt; -Isources sources/*.c -o
&lt;model&gt;.so -lm</code>. See docs/fmus.md in the platoon-cosim repository.</p>"""


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


def sources_of(name: str) -> tuple[str, ...]:
    """The C files compiled into FMU ``name``, as listed in its model description."""
    return (MODEL_SOURCE[name],) + COMMON_SOURCES


def _c_string(text: str) -> str:
    return json.dumps(text)  # ASCII names and values: JSON's escapes are C's


def variables_header(slave, guid: str) -> str:
    """The generated C header of one model: GUID, value references, the variable table."""
    cls = type(slave)
    reference_of = {variable.name: reference for reference, variable in slave.vars.items()}
    by_reference = sorted(cls.variables, key=lambda info: reference_of[info.name])
    if [reference_of[info.name] for info in by_reference] != list(range(len(by_reference))):
        raise BuildError(f"{cls.__name__}: value references are not 0..n-1; the C table is indexed by them")
    lines = [
        f"/* Generated by fmus/native_build.py from fmus/slaves/{cls.__name__}.py: do not edit. */",
        "#ifndef PLATOON_VARIABLES_H", "#define PLATOON_VARIABLES_H", "", '#include "framework.h"', "",
        f"#define MODEL_IDENTIFIER {_c_string(cls.__name__)}",
        f"#define MODEL_GUID {_c_string(guid)}",
        f"#define VARIABLE_COUNT {len(by_reference)}", "",
    ]
    for info in by_reference:
        macro = "VR_" + "".join(c if c.isalnum() else "_" for c in info.name).upper()
        lines.append(f"#define {macro} {reference_of[info.name]} /* {info.type} {info.causality} */")
    lines += ["", "static const VariableDef MODEL_VARIABLES[VARIABLE_COUNT] = {"]
    for info in by_reference:
        start_real = repr(float(info.start)) if info.type == "Real" and info.start is not None else "0.0"
        start_integer = int(info.start) if info.type in ("Integer", "Boolean") else 0
        start_string = _c_string(info.start) if info.type == "String" else "NULL"
        lines.append(f"    {{{_c_string(info.name)}, VAR_{info.type.upper()}, CAUSALITY_{info.causality.upper()}, "
                     f"{start_real}, {start_integer}, {start_string}}},")
    lines += ["};", "", "#endif", ""]
    return "\n".join(lines)


def _digest(name: str) -> str:
    """Digest of everything that shapes FMU ``name`` but its GUID (which is made from it), read from files
    only: the C sources, the Python declarations the generated header, model description and
    documentation come from (the pythonfmu FMU's sources, fmus.build.bundled_sources), the builder
    modules, FMI's headers, the compiler flags and pythonfmu's version (it numbers the variables).

    No slave is instantiated and no compiler is asked: a run checks its FMUs with this before every
    start (issue 22), and FMUs built elsewhere are usable on a machine without a compiler. The
    compiler's identity is not part of it: with -ffp-contract=off every compiler gives the numbers of
    fmus/model (tests/test_native_fmus.py), so the GUID names the model, not the compiler's bytes."""
    digest = hashlib.sha256(importlib.metadata.version("pythonfmu").encode())
    digest.update(" ".join(CFLAGS + LIBS).encode())
    files = [NATIVE_SOURCES / file for file in sorted(set(sources_of(name) + HEADERS))]
    files += bundled_sources(name)
    files += [PACKAGE_DIR / module for module in ("native_build.py", "build.py", "modeldescription.py",
                                                  "documentation.py")]
    files += [fmi_headers() / file for file in FMI_HEADERS]
    for path in files:
        digest.update(path.name.encode())
        digest.update(hashlib.sha256(path.read_bytes()).digest())
    return digest.hexdigest()


def binary_entry(name: str) -> str:
    platform, suffix = fmi_platform()
    return f"binaries/{platform}/{name}{suffix}"


def is_complete(path: Path, name: str, guid: str) -> bool:
    """``path`` is an intact native build of ``name`` with ``guid``: every CRC passes and the binary
    and the sources are there."""
    required = {binary_entry(name)} | {f"sources/{file}" for file in sources_of(name) + HEADERS + (GENERATED_HEADER,)}
    return archive_is_whole(path, guid, required)


def compile_binary(name: str, header: str, cc: str, scratch: Path, files: tuple[str, ...] | None = None,
                   generated: dict[str, str] | None = None) -> bytes:
    """The shared library of FMU ``name``, compiled in ``scratch`` from copies of the sources: the C
    ``files`` (default: this FMI 2.0 build's, ``sources_of(name)``; the FMI 3.0 build, fmus/native_build3.py,
    swaps fmi2.c for fmi3.c) with variables.h and any further ``generated`` headers (name: text)."""
    files = files or sources_of(name)
    sources = scratch / "sources"
    sources.mkdir()
    for file in files + HEADERS:
        shutil.copyfile(NATIVE_SOURCES / file, sources / file)
    for file, text in {GENERATED_HEADER: header, **(generated or {})}.items():
        (sources / file).write_text(text)
    output = scratch / f"{name}.so"
    command = [cc, *CFLAGS, f"-I{fmi_headers()}", "-I.", *files, "-o", str(output), *LIBS]
    result = subprocess.run(command, cwd=sources, capture_output=True, text=True, timeout=600)
    if result.returncode != 0:
        raise BuildError(f"{name}: compiling the native FMU failed ({' '.join(command)}):\n{result.stderr.strip()}")
    return output.read_bytes()


def _build_one(name: str, slave, guid: str, cc: str, out_dir: Path) -> Path:
    from fmus.documentation import documentation_html
    from fmus.modeldescription import model_description

    header = variables_header(slave, guid)
    with tempfile.TemporaryDirectory(prefix="platoon-native-") as scratch:
        binary = compile_binary(name, header, cc, Path(scratch))
    entries = {
        "modelDescription.xml": model_description(slave, guid, fmus.__version__, RUNTIME, CAPABILITIES_NATIVE,
                                                  sources_of(name)),
        "documentation/index.html": documentation_html(slave, fmus.__version__, NATIVE_HOST).encode(),
        binary_entry(name): binary,
        f"sources/{GENERATED_HEADER}": header.encode(),
    }
    for file in sources_of(name) + HEADERS:
        entries[f"sources/{file}"] = (NATIVE_SOURCES / file).read_bytes()
    return write_fmu(out_dir / f"{name}.fmu", entries)


def expected_guid(name: str) -> str:
    return guid_for(_digest(name), f"native:{name}")


def build_native_fmus(out_dir: Path = NATIVE_OUT, force: bool = False,
                      names: tuple[str, ...] = FMU_NAMES) -> list[BuiltFmu]:
    """Build the native FMUs ``names`` into ``out_dir`` unless an up-to-date one is already there.
    Raises NoCompiler (one line) when one must be built and there is no C compiler, BuildError when
    compiling fails. Up-to-date FMUs need no compiler (nor pythonfmu: nothing is imported to check)."""
    return build_stale(out_dir, force, names, expected_guid, is_complete,
                       lambda name, guid, folder: _build_one(name, _slave_instance(name), guid, compiler(), folder))


def model_description_of(path: Path) -> ElementTree.Element:
    with zipfile.ZipFile(path) as archive:
        return ElementTree.fromstring(archive.read("modelDescription.xml"))
