"""The native builder: the Vehicle and VirtualTarget FMUs compiled from C (fmus/native/), as FMI 2.0
or FMI 3.0 co-simulation FMUs (``NativeBuilder(fmi_version)``).

The pythonfmu FMUs need a Python installation on the host; these twins need nothing but the C
library. Their C files mirror fmus/model equation by equation; what they share with the pythonfmu
FMUs is taken from the same Python declarations at build time, so nothing is written twice:

* ``variables.h`` (generated into the build): every variable's value reference (the one pythonfmu
  gives it), name, type, causality and start value, and the build's GUID (FMI 3.0: the
  instantiationToken, which fmi3.c compares with the host's);
* ``modelDescription.xml``: ``fmus.modeldescription.fmi2`` (the native capability flags,
  needsExecutionTool="false": the binary runs the model itself, and the C files listed as sources) or
  ``fmus.modeldescription.fmi3`` (the same value references, plus the independent variable ``time``);
* ``documentation/index.html``: ``fmus.documentation``, with the native host requirements;
* FMI 3.0 only: ``fmi3config.h`` (the value reference of ``time``) and ``sources/buildDescription.xml``
  (FMI 3.0's list of the sources, section 2.5.1, "Directory sources"), so an importer that compiles
  FMUs (FMPy) can build the binary for its own platform.

The two versions share the model file and framework and differ only in the FMI layer (fmi2.c or
fmi3.c), so both compute the same numbers. The FMU also carries the C sources and the generated headers
(``sources/``), so it can be compiled for another platform with one compiler command (docs/fmus.md).
The GUID is a digest of everything that shapes the FMU (C sources, the Python declarations behind the
generated header and model description, builder, compiler flags, FMI headers: ``_digest``), so an FMU is
rebuilt exactly when one of them changes; the archive is written aside and moved into place
(``fmus.builders.base.write_fmu``), reproducibly.
"""

from __future__ import annotations

import hashlib
import json
import tempfile
import time
from pathlib import Path
from typing import Callable
from xml.etree.ElementTree import Element, SubElement

import fmus
from fmus.builders.base import DEFAULT_OUT, PACKAGE_DIR, Builder, BuildError, slave_instance
from fmus.builders.pythonfmu import bundled_sources, pythonfmu_version
from fmus.builders.toolchain import (CFLAGS, FMI_HEADERS, HEADERS, LIBS, NATIVE_SOURCES, compile_binary, fmi_headers,
                                     universal_binary)
from fmus.modeldescription import fmi2, fmi3
from fmus.modeldescription.core import instantiation_token, serialize
from fmus.platforms import RELEASE_PLATFORMS, Platform, binary_entry, host_platform, release_layout

NATIVE_OUT = DEFAULT_OUT / "native"
FMI3_OUT = DEFAULT_OUT / "fmi3"
MODEL_SOURCE = {"Vehicle": "vehicle.c", "VirtualTarget": "target.c", "Link": "link.c"}
GENERATED_HEADER = "variables.h"
CONFIG_HEADER = "fmi3config.h"  # FMI 3.0 only
BUILD_DESCRIPTION = "sources/buildDescription.xml"  # FMI 3.0 only
# the modules (below fmus/) that shape what this builder writes: a change to one rebuilds the FMUs
BUILDER_MODULES = ("builders/base.py", "builders/native.py", "builders/pythonfmu.py", "builders/toolchain.py",
                   "modeldescription/core.py", "modeldescription/fmi2.py", "modeldescription/fmi3.py",
                   "documentation.py", "platforms.py")

CAPABILITIES_NATIVE = fmi2.CAPABILITIES | {"needsExecutionTool": "false"}
RUNTIME = "native C"

NATIVE_HOST = """<p>A native FMU: its binary is compiled C (this FMU's <code>sources/</code>) and needs nothing on the
host but the C library and its math library: no Python, no environment variables. To build it for another platform:
<code>cc -std=c99 -O2 -fPIC -shared -ffp-contract=off -I&lt;FMI 2.0 headers&gt; -Isources sources/*.c -o
&lt;model&gt;.so -lm</code>. See docs/fmus.md in the platoon-cosim repository.</p>"""
NATIVE_HOST3 = """<p>A native FMI 3.0 FMU: its binary is compiled C (this FMU's <code>sources/</code>, listed in
<code>sources/buildDescription.xml</code>) and needs nothing on the host but the C library and its math library: no
Python, no environment variables. To build it for another platform:
<code>cc -std=c99 -O2 -fPIC -shared -ffp-contract=off -I&lt;FMI 3.0 headers&gt; -Isources sources/*.c -o
&lt;model&gt;.so -lm</code>. See docs/fmus.md in the platoon-cosim repository.</p>
<p>FMI 3.0: the table below names the types as the FMI 2.0 twins do; here Real is <code>Float64</code> and
Integer <code>Int32</code>, with the same value references, and the independent variable <code>time</code> has
value reference """ + str(fmi3.TIME_VALUE_REFERENCE) + """ (readable, never set).</p>"""
NATIVE_HOST_OF = {2: NATIVE_HOST, 3: NATIVE_HOST3}


def sources_of(name: str, fmi_version: int = 2) -> tuple[str, ...]:
    """The C files compiled into FMU ``name``: the model, the framework and the FMI layer (as listed in
    its model description, FMI 2.0, or its buildDescription.xml, FMI 3.0)."""
    return (MODEL_SOURCE[name], "framework.c", f"fmi{fmi_version}.c")


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
        f"/* Generated by fmus/builders/native.py from fmus/slaves/{cls.__name__}.py: do not edit. */",
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


def config_header() -> str:
    """The generated header of what fmi3.c needs from the FMI 3.0 model description."""
    return "\n".join([
        "/* Generated by fmus/builders/native.py from fmus/modeldescription/fmi3.py: do not edit. */",
        "#ifndef PLATOON_FMI3CONFIG_H", "#define PLATOON_FMI3CONFIG_H", "",
        "/* the value reference of the independent variable `time` */",
        f"#define PLATOON_TIME_VALUE_REFERENCE {fmi3.TIME_VALUE_REFERENCE}u", "", "#endif", "",
    ])


def build_description(name: str) -> bytes:
    """sources/buildDescription.xml: the C files of FMU ``name`` and where its headers are."""
    root = Element("fmiBuildDescription", {"fmiVersion": "3.0"})
    configuration = SubElement(root, "BuildConfiguration", {"modelIdentifier": name})
    file_set = SubElement(configuration, "SourceFileSet", {"language": "C99"})
    for file in sources_of(name, 3):
        SubElement(file_set, "SourceFile", {"name": file})
    SubElement(file_set, "IncludeDirectory", {"name": "."})
    SubElement(configuration, "Library", {"name": "m", "external": "true",
                                          "description": "the C math library (link with -lm)"})
    return serialize(root)


class NativeBuilder(Builder):
    """The native FMUs of one FMI version (2 or 3): with the binary for this machine, or with
    ``all_platforms`` the binaries for every platform of ``fmus.platforms.RELEASE_PLATFORMS``,
    cross-compiled with Zig (``fmus.builders.toolchain``). Both have the same GUID: it names the model,
    and the binaries compute the same numbers (tests/test_platforms.py). A release FMU serves as a
    current host build too; a host build is rebuilt when all platforms are asked for."""

    kind = "native"

    def __init__(self, fmi_version: int, all_platforms: bool = False,
                 compiled: Callable[[str, Platform, float], None] | None = None) -> None:
        """``compiled(what, platform, seconds)`` after each binary of an ``all_platforms`` build (what: e.g.
        "Vehicle.fmu, FMI 2.0"; thirty compilations: the caller shows them as they finish)."""
        if fmi_version not in (2, 3):
            raise ValueError(f"FMI version {fmi_version!r}: the native FMUs are built as FMI 2 or 3")
        self.fmi_version = fmi_version
        self.all_platforms = all_platforms
        self.compiled = compiled
        self.default_out = NATIVE_OUT if fmi_version == 2 else FMI3_OUT

    def __repr__(self) -> str:
        return f"NativeBuilder(fmi_version={self.fmi_version}, all_platforms={self.all_platforms})"

    def _digest(self, name: str) -> str:
        """Digest of everything that shapes FMU ``name`` but its GUID (which is made from it), read from files
        only: the C sources, the Python declarations the generated headers, model description and
        documentation come from (the pythonfmu FMU's sources, ``bundled_sources``), the builder
        modules, FMI's headers, the compiler flags and pythonfmu's version (it numbers the variables).

        No slave is instantiated and no compiler is asked: a run checks its FMUs with this before every
        start (so it must be cheap: a sweep is made of short runs), and FMUs built elsewhere are usable on a machine without a compiler. The
        compiler's identity is not part of it: with -ffp-contract=off every compiler gives the numbers of
        fmus/model (tests/test_native_fmus.py), so the GUID names the model, not the compiler's bytes."""
        digest = hashlib.sha256(pythonfmu_version().encode())
        digest.update(" ".join(CFLAGS + LIBS).encode())
        for path in self.digest_files(name):
            digest.update(path.name.encode())
            digest.update(hashlib.sha256(path.read_bytes()).digest())
        return digest.hexdigest()

    def digest_files(self, name: str) -> list[Path]:
        """The files ``_digest`` reads for FMU ``name``, in its order (the compiler flags are in toolchain.py,
        one of them)."""
        files = [NATIVE_SOURCES / file for file in sorted(set(sources_of(name, self.fmi_version) + HEADERS))]
        files += bundled_sources(name)
        files += [PACKAGE_DIR / module for module in BUILDER_MODULES]
        return files + [fmi_headers() / file for file in FMI_HEADERS[self.fmi_version]]

    def expected_guid(self, name: str) -> str:
        return instantiation_token(self._digest(name), f"native:{name}", self.fmi_version)

    def binary_entry(self, name: str, platform: Platform | None = None) -> str:
        """The binary's place in the FMU, for ``platform`` (default: this machine)."""
        return binary_entry(name, self.fmi_version, platform)

    def generated_headers(self, slave, guid: str) -> dict[str, str]:
        """The headers made from the declarations (file name: text), compiled in and shipped in sources/."""
        headers = {GENERATED_HEADER: variables_header(slave, guid)}
        if self.fmi_version == 3:
            headers[CONFIG_HEADER] = config_header()
        return headers

    def binary_entries(self, name: str) -> dict[str, tuple[Platform, ...]]:
        """The binaries of FMU ``name`` (archive entry: the platforms it is built for; two are one
        universal binary)."""
        if not self.all_platforms:
            return {self.binary_entry(name): (host_platform(),)}
        return {f"binaries/{folder}/{name}{platforms[0].suffix}": platforms
                for folder, platforms in release_layout(self.fmi_version).items()}

    def required_entries(self, name: str) -> set[str]:
        """The binaries (this machine's, or every release platform's) and every source (an importer may
        compile them)."""
        generated = (GENERATED_HEADER,) if self.fmi_version == 2 else (GENERATED_HEADER, CONFIG_HEADER)
        files = sources_of(name, self.fmi_version) + HEADERS + generated
        required = set(self.binary_entries(name)) | {f"sources/{file}" for file in files}
        return required | ({BUILD_DESCRIPTION} if self.fmi_version == 3 else set())

    def model_description(self, name: str, slave, guid: str) -> bytes:
        if self.fmi_version == 2:
            return fmi2.model_description(slave, guid, fmus.__version__, RUNTIME, CAPABILITIES_NATIVE, sources_of(name))
        return fmi3.model_description(type(slave), guid, fmus.__version__)

    def entries(self, name: str, slave, guid: str, binaries: dict[str, bytes]) -> dict[str, bytes]:
        """Everything in FMU ``name`` with ``guid``: ``binaries`` (archive entry: bytes) and the rest."""
        from fmus.documentation import documentation_html  # only to build (html.entities: start-up time of a run)

        entries = {
            "modelDescription.xml": self.model_description(name, slave, guid),
            "documentation/index.html": documentation_html(slave, fmus.__version__,
                                                           NATIVE_HOST_OF[self.fmi_version]).encode(),
            **binaries,
        }
        for file, text in self.generated_headers(slave, guid).items():
            entries[f"sources/{file}"] = text.encode()
        if self.fmi_version == 3:
            entries[BUILD_DESCRIPTION] = build_description(name)
        for file in sources_of(name, self.fmi_version) + HEADERS:
            entries[f"sources/{file}"] = (NATIVE_SOURCES / file).read_bytes()
        return entries

    def build_one(self, name: str, guid: str) -> dict[str, bytes]:
        slave = slave_instance(name)
        files, headers = sources_of(name, self.fmi_version), self.generated_headers(slave, guid)
        with tempfile.TemporaryDirectory(prefix=f"platoon-native{self.fmi_version}-") as scratch:
            if not self.all_platforms:
                binaries = {self.binary_entry(name): compile_binary(name, files, headers, Path(scratch))}
            else:
                thin = {platform: self._cross_compile(name, files, headers, Path(scratch), platform)
                        for platform in RELEASE_PLATFORMS}
                binaries = {entry: thin[platforms[0]] if len(platforms) == 1
                            else universal_binary([thin[platform] for platform in platforms])
                            for entry, platforms in self.binary_entries(name).items()}
        return self.entries(name, slave, guid, binaries)

    def _cross_compile(self, name: str, files: tuple[str, ...], headers: dict[str, str], scratch: Path,
                       platform: Platform) -> bytes:
        """FMU ``name``'s binary for ``platform``, said to ``compiled`` once done."""
        started = time.monotonic()
        binary = compile_binary(name, files, headers, scratch / platform.tuple, platform)
        if self.compiled is not None:
            self.compiled(f"{name}.fmu, FMI {self.fmi_version}.0", platform, time.monotonic() - started)
        return binary
