"""Zig's cache warmed before anything times a cross-compilation (``platoon build --all-platforms``).

Not one of the builder's modules (native.py: ``BUILDER_MODULES``): what it does never changes an FMU.
Run as ``python -m fmus.builders.zig_cache`` it warms the cache and prints what each target took.
"""

from __future__ import annotations

import sys
import tempfile
import time
from pathlib import Path
from typing import Callable

from fmus.builders.base import BuildError
from fmus.builders.toolchain import (DEFAULT_WARM_TIMEOUT, LIBS, ZIG_TARGETS, compile_timeout, cross_flags, run_compiler,
                                     zig_cc, zig_timeout_text)

# What a first cross-compilation for a target costs, paid once per machine: Zig builds that target's C
# library stubs (glibc 2.17, MinGW-w64's CRT, macOS's libSystem) and compiler-rt from source into its
# global cache (``zig env``: global_cache_dir, ~/.cache/zig unless $ZIG_GLOBAL_CACHE_DIR). A tiny
# library compiled with the release flags builds exactly those; every later compile for the target
# only compiles its own files. The function is exported, as an FMU's are: Zig's Mach-O linker crashes
# (SIGSEGV, Zig 0.17.1) on a stripped dylib that exports nothing.
WARM_SOURCE = '__attribute__((visibility("default"))) double platoon_warm(double x) { return x * 2.0; }\n'


def warm_cross_cache(ready: Callable[[str, float], None] | None = None,
                     waiting: Callable[[str, float], None] | None = None, every: float = 5.0) -> dict[str, float]:
    """Build Zig's C library stubs and compiler-rt for every release target into its global cache, so
    that the first ``platoon build --all-platforms`` costs what any later one does (the tests that run it
    under a time budget call this first). Returns the seconds each target took (a fraction of a second
    each when the cache is warm already); ``ready(target, seconds)`` as each one is done, ``waiting(target,
    seconds so far)`` every ``every`` s while one takes longer (a cold cache: minutes). ``NoCrossCompiler``
    without the ziglang package; ``CompileTimeout`` (one line: the target, what to do) past the warm-up's
    timeout (``PLATOON_COMPILE_TIMEOUT``, default 1800 s: this compile is the slow one by design), the
    compiler stopped."""
    taken = {}
    with tempfile.TemporaryDirectory(prefix="platoon-zig-warm-") as scratch:
        source = Path(scratch) / "warm.c"
        source.write_text(WARM_SOURCE)
        for platform, target in ZIG_TARGETS.items():
            started = time.monotonic()
            output = Path(scratch) / f"warm-{platform.tuple}{platform.suffix}"
            command = [*zig_cc(), *cross_flags("warm", platform), str(source), "-o", str(output), *LIBS]
            result = run_compiler(command, Path(scratch), lambda limit, target=target: zig_timeout_text(target, limit),
                                  None if waiting is None else (lambda seconds, target=target: waiting(target, seconds)),
                                  every, compile_timeout(DEFAULT_WARM_TIMEOUT))
            if result.returncode != 0:
                raise BuildError(f"warming Zig's cache for {platform.tuple} failed ({' '.join(command)}):\n"
                                 f"{result.stderr.strip()}")
            taken[platform.tuple] = time.monotonic() - started
            if ready is not None:
                ready(target, taken[platform.tuple])
    return taken


def main() -> None:
    """Warm the cache, printing each target's seconds and the total; the error and exit 1 if it fails."""
    import argparse

    argparse.ArgumentParser(prog="python -m fmus.builders.zig_cache",
                            description="Compile a small C file for every target of `platoon build --all-platforms` "
                                        "so that Zig's cache holds their C runtimes (minutes when cold, about a "
                                        "second when warm); prints each target's seconds.").parse_args()
    began = time.monotonic()
    try:
        warm_cross_cache(lambda target, seconds: print(f"zig cache: {target} {seconds:.1f} s", flush=True),
                         lambda target, seconds: print(f"zig cache: {target}: building its C runtime, {seconds:.0f} s "
                                                       "so far", flush=True))
    except BuildError as error:
        sys.exit(f"error: {error}")
    print(f"zig cache warm in {time.monotonic() - began:.1f} s", flush=True)


if __name__ == "__main__":  # python -m fmus.builders.zig_cache: what .ci/run does before the slow tests
    main()
