"""Keep a Python host from aborting, or from hanging, at exit after it ran one of our FMUs.

Hanging: an FMU that holds threads of the host's interpreter (LiveVehicle.fmu: Zenoh runs each
subscriber's callbacks on a non-daemon Python thread, "pyo3-closure", parked in a receive until the
subscriber is undeclared) keeps a host that never freed it, or frees it only when its objects are
collected, from exiting: the interpreter's shutdown first joins every non-daemon thread, before any
``atexit`` handler or object finalizer runs. ``close_at_host_exit`` closes such an FMU's resources
just before that join (``threading._register_atexit``: the hook concurrent.futures uses to stop its
workers, called at the start of ``threading._shutdown``), so the host exits as if it had freed it.

Aborting: pythonfmu's binary (0.7.0, the latest release) keeps a global ``std::shared_ptr<PyState>`` and also
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
import itertools
import os
import sys
import threading
from pathlib import Path
from typing import Callable

_GUARDED: set[str] = set()
_CLOSERS: dict[int, Callable[[], None]] = {}  # what close_at_host_exit still has to close, by ticket
_TICKETS = itertools.count()
_HOOKED = threading.Lock()
_hooked = False


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


def _close_all() -> None:
    """At the start of the interpreter's shutdown: close what is still open, newest first."""
    while _CLOSERS:
        _, close = _CLOSERS.popitem()
        try:
            close()
        except Exception as error:  # noqa: BLE001 - the host is exiting: say it, and close the others
            print(f"at exit: {error}", file=sys.stderr)


def close_at_host_exit(close: Callable[[], None]) -> Callable[[], None]:
    """Have ``close`` called when the interpreter begins to exit, before it joins its threads, unless the
    returned function (call it when ``close`` ran otherwise: fmi2Terminate, fmi2FreeInstance) withdrew it."""
    global _hooked
    ticket = next(_TICKETS)
    with _HOOKED:
        if not _hooked:
            try:
                threading._register_atexit(_close_all)  # type: ignore[attr-defined]
            except RuntimeError:  # the interpreter is already exiting: nothing will join our threads any more
                return lambda: None
            _hooked = True
        _CLOSERS[ticket] = close

    def withdraw() -> None:
        _CLOSERS.pop(ticket, None)

    return withdraw
