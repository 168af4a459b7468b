"""Keep a Python host from aborting at exit after it ran one of our FMUs.

pythonfmu's binary (0.7.0, the latest release) keeps a global ``std::shared_ptr<PyState>`` and also
resets it from a library destructor (``finalizePythonInterpreter``, ``__attribute__((destructor))``).
When the host is a Python process, the library is usually still mapped when the process exits, and
glibc then runs the C++ exit handlers first (destroying the shared pointer, freeing its block) and the
library destructor afterwards, which releases the freed block a second time. valgrind shows it as
"Invalid read of size 4 in finalizePythonInterpreter ... inside a block free'd by __run_exit_handlers";
glibc sometimes notices and aborts the host ("free(): corrupted unsorted chunks", exit 134) after
the simulation's results were already printed, e.g. a plain ``fmpy.simulate_fmu`` script (pythonfmu's
https://github.com/NTNU-IHB/PythonFMU/issues/228 reports the same message).

The fix from inside the FMU: when the host's own interpreter runs us, register a Python exit handler
that calls the library's exported ``finalizePythonInterpreter`` while everything is still alive.
That empties the shared pointer (its PyState owns nothing in that case: the host, not the FMU,
initialized Python), so both later resets find nothing to free.

Only when the host owns the interpreter: if the FMU's binary started Python itself (a C host), its
interpreter was initialized on pythonfmu's worker thread and finalizes from inside that reset, where
a second reset would itself free twice. On Linux the process's main thread has the process id as its
thread id, which tells the two cases apart.
"""

from __future__ import annotations

import atexit
import ctypes
import os
import sys
import threading
from pathlib import Path

_GUARDED: set[str] = set()


def _host_owns_the_interpreter() -> bool:
    return threading.main_thread().native_id == os.getpid()


def _binary_of(resources: str, model_identifier: str) -> Path:
    return Path(resources).parent / "binaries" / "linux64" / f"{model_identifier}.so"


def _release_python_state(binary: str) -> None:
    """Empty the binary's PyState pointer now, if the binary is still loaded (the host may have
    unloaded it already, which ran the same reset in the right order)."""
    try:
        library = ctypes.CDLL(binary, mode=os.RTLD_NOLOAD | os.RTLD_LAZY)
    except OSError:
        return
    release = getattr(library, "finalizePythonInterpreter", None)
    if release is not None:
        release()


def guard_host_exit(resources: str | None, model_identifier: str) -> None:
    """Arrange the early reset for this FMU's binary (once per binary per process)."""
    if not sys.platform.startswith("linux") or not resources or not _host_owns_the_interpreter():
        return
    binary = str(_binary_of(resources, model_identifier))
    if binary in _GUARDED or not os.path.isfile(binary):
        return
    _GUARDED.add(binary)
    atexit.register(_release_python_state, binary)
