"""The run-time error every engine and the trace writer raise for a failing component.

Kept in a module of its own (no FMPy, no numpy) so that a trace-writing worker process can raise and
report it without importing the FMI side.
"""

from __future__ import annotations

import re

# How pythonfmu 0.7's binary logs a call our FMUs refuse (fmus/slaves/refusal.py): a line of its own,
# then the reason. The engines report the FMU's last log line; only the reason is worth a line.
_PYTHONFMU_PREFIX = re.compile(r"^Fatal py exception encountered: \[\w+\] PyObject_CallMethod\n")


def readable_reason(reason: str) -> str:
    """``reason`` on one line, without pythonfmu's boilerplate first line."""
    return " ".join(_PYTHONFMU_PREFIX.sub("", reason).split())


class ComponentError(RuntimeError):
    """A component failed; the message names the component, the time and the reason."""

    def __init__(self, component: str, time: float, reason: str) -> None:
        reason = readable_reason(reason)
        super().__init__(f"{component} failed at t = {time:.6g} s: {reason}")
        self.component, self.time, self.reason = component, time, reason

    def __reduce__(self):  # picklable with its three fields (a worker process sends it back)
        return (type(self), (self.component, self.time, self.reason))
