"""Build configuration for the compiled parts: the native stepping core (orchestrator/execution/native/_core.c) and
the trace encoder (orchestrator/trace/native_encoder.c).

Everything else about the package is in pyproject.toml. The extension uses only the CPython C API and
dlopen (no numpy headers, no build dependency beyond setuptools and a C compiler). It is optional: on
a machine without a C compiler the install still succeeds and the Python engine is used
(``orchestrator.execution.native.available()`` says which).
"""

import sys

from setuptools import Extension, setup

compile_args = [] if sys.platform == "win32" else [
    "-O2",
    "-std=c99",
    "-D_GNU_SOURCE",  # strdup
    "-ffp-contract=off",  # no fused multiply-add: t0 + k*h rounds exactly as in Python
    "-fno-fast-math",
]

setup(
    ext_modules=[
        Extension(
            "orchestrator.execution.native._core",
            sources=["orchestrator/execution/native/_core.c"],
            libraries=["dl"] if sys.platform.startswith("linux") else [],
            extra_compile_args=compile_args,
            optional=True,
        ),
        # the trace's per-row messages (orchestrator/trace/native_encoder.c; orchestrator/trace/native_rows.py):
        # a module of its own, so that a trace can be encoded in C by a process that steps nothing (the trace
        # worker) and the stepping core stays one job
        Extension(
            "orchestrator.trace._native",
            sources=["orchestrator/trace/native_encoder.c"],
            include_dirs=["fmus/native"],  # pymath.h: math.hypot to the last bit
            extra_compile_args=compile_args,
            optional=True,
        ),
        # the read side's twin: a trace chunk's JSON messages decoded into float64 columns
        # (orchestrator/trace/native_decoder.c, driven by orchestrator/trace/columns.py)
        Extension(
            "orchestrator.trace._decode",
            sources=["orchestrator/trace/native_decoder.c"],
            extra_compile_args=compile_args,
            optional=True,
        ),
    ]
)
