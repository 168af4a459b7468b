"""How one FMI call of ours fails without crashing the host: the only door out for an exception.

pythonfmu 0.7.0's binary (``PySlaveInstance.cpp``) turns a Python exception from any slave method
into fmi2Fatal, and on the way (``handle_py_exception`` -> ``cleanPyObject``) it drops its references
to the slave instance, the slave class and the log queue without forgetting the pointers. Once our
instance was its last owner, the next call (the host's fmi2GetReal, fmi2FreeInstance) runs on freed
memory: the host segfaults (tests/test_hostile_fmus.py calls them so).

The binary reports a failure in no other way. It ignores what ``exit_initialization_mode``, the
getters, the setters and the state methods return, so only an exception can fail them; only
``do_step`` has a return value it maps (False -> fmi2Discard). So a call that must fail raises,
through ``refuse`` alone: it gives each of the three objects the binary is about to release one
extra reference (``Py_IncRef``, owned by nobody, so the binary's unbalanced decrement takes exactly
that one), the instance stays alive, and every later call on it runs on live objects and fails (or
works) cleanly. Held in a list instead, the extra reference would be released twice in the end (by
the binary and by the list): the instance was then freed while still listed, and the next garbage
collection crashed the host (measured: a Python and a native engine run in one process).

The reason travels in the exception: the binary logs it, with status fmi2Fatal, as
``Fatal py exception encountered: [getReal] PyObject_CallMethod\n<reason>`` (a host
sees it when logging is on). It must be the only message of the call: the binary flushes the log
queue before it reads the exception, and with a message queued the exception is lost on the way
(the host then reads "unknown error", measured). So a call that refuses logs nothing else first.

``fmi_call`` wraps each method the binary calls, so an unforeseen exception (a bug, an input nobody
thought of) also leaves through ``refuse``, never raw; ``fmi_step`` turns one from a ``do_step`` into
a logged fmi2Discard. ``PlatoonSlave.__init_subclass__`` applies them to every subclass's overrides
too (LiveVehicle's), so no slave can forget it.

The status a host sees for a refused call is therefore fmi2Fatal, not the fmi2Error the call
deserves: the binary offers nothing else (docs/fmus.md, "Failures").

The same binary has a second unbalanced decrement, on every fmi2Instantiate: ``findClass`` releases
the slave module's globals dictionary, a borrowed reference (``PyModule_GetDict``). In a host that
instantiates an FMU again and again in one process (a test suite, a parameter sweep), the dictionary
is freed once its real references are used up, and the next fmi2Instantiate segfaults (measured:
the second instantiation of a slave module that defines no functions; FMPy's simulate_fmu twice in
one process). findClass first re-executes the module's source in those globals, which runs the slave
class statement again, so ``keep_module_globals``, called from ``__init_subclass__``, hands it the
reference it will drop just in time, once per call.
"""

from __future__ import annotations

import ctypes
import functools
import sys
from typing import Any, Callable, NoReturn, TypeVar

from pythonfmu.enums import Fmi2Status

_incref = ctypes.pythonapi.Py_IncRef
_incref.argtypes = [ctypes.py_object]
_incref.restype = None


def _reference_for_the_binary(thing: Any) -> None:
    """One reference to ``thing`` that the binary's unbalanced Py_DECREF will take."""
    _incref(thing)

Method = TypeVar("Method", bound=Callable[..., Any])


class CallRefused(Exception):
    """One FMI call failed; the message is the reason, as logged."""

    def __repr__(self) -> str:  # the binary logs repr(exception): the reason alone reads best
        return str(self)


def refuse(slave: Any, reason: str) -> NoReturn:
    """Fail the current FMI call of ``slave`` with ``reason``, keeping the instance alive."""
    # The three objects cleanPyObject() releases: pClass_, pInstance_, pMessages_.
    for thing in (type(slave), slave, slave._get_log_queue()):
        _reference_for_the_binary(thing)
    raise CallRefused(reason)


def keep_module_globals(cls: type) -> None:
    """Called by every slave class statement: one reference to its module's globals for findClass
    to release."""
    module = sys.modules.get(cls.__module__)
    if module is not None:
        _reference_for_the_binary(vars(module))


def fmi_step(method: Method) -> Method:
    """A subclass's ``do_step`` as the binary may call it: an exception becomes a logged fmi2Discard."""

    @functools.wraps(method)
    def step(self: Any, current_time: float, step_size: float) -> bool:
        try:
            return bool(method(self, current_time, step_size))
        except Exception as error:  # noqa: BLE001
            self.log(f"{self.instance_name}: step from t = {current_time:.6g} s failed: {type(error).__name__}: "
                     f"{error}", Fmi2Status.error)
            return False

    return step  # type: ignore[return-value]


def fmi_call(method: Method) -> Method:
    """``method`` as the binary may call it: any exception leaves through ``refuse``."""

    @functools.wraps(method)
    def call(self: Any, *args: Any) -> Any:
        try:
            return method(self, *args)
        except CallRefused:
            raise
        except Exception as error:  # noqa: BLE001 - whatever it is, the host must survive it
            refuse(self, f"{self.instance_name}: {method.__name__} failed: {type(error).__name__}: {error}")

    return call  # type: ignore[return-value]
