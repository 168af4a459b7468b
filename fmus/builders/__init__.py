"""`platoon build`: one ``Builder`` per FMU kind, the FMI version a parameter.

* ``PYTHONFMU``: the slaves (fmus/slaves) as FMI 2.0 FMUs packaged by pythonfmu (``build/fmus``);
* ``NATIVE_FMI2``, ``NATIVE_FMI3``: their C twins (fmus/native) as FMI 2.0 and FMI 3.0 FMUs
  (``build/fmus/native``, ``build/fmus/fmi3``): ``NativeBuilder(fmi_version)``.

Each builds an FMU only when it is missing, stale (its GUID no longer matches the sources) or damaged
(``Builder.build``); the binaries' folders come from ``fmus.platforms``.
"""

from fmus.builders.base import (ALL_FMUS, DEFAULT_OUT, FMU_NAMES, LINK_FMU, LIVE_FMU, REMOTE_FMU, Builder, BuildError,
                                BuiltFmu, fmu_guid)
from fmus.builders.native import FMI3_OUT, NATIVE_OUT, NativeBuilder
from fmus.builders.pythonfmu import PythonFmuBuilder, bundled_sources
from fmus.builders.toolchain import NoCompiler, compiler

PYTHONFMU = PythonFmuBuilder()
NATIVE_FMI2 = NativeBuilder(fmi_version=2)
NATIVE_FMI3 = NativeBuilder(fmi_version=3)

__all__ = ["ALL_FMUS", "DEFAULT_OUT", "FMI3_OUT", "FMU_NAMES", "LINK_FMU", "LIVE_FMU", "NATIVE_FMI2", "NATIVE_FMI3", "NATIVE_OUT",
           "PYTHONFMU", "REMOTE_FMU", "Builder", "BuildError", "BuiltFmu", "NativeBuilder", "NoCompiler", "PythonFmuBuilder",
           "bundled_sources", "compiler", "fmu_guid"]
