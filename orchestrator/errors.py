"""The run-time error every engine and the trace writer raise for a failing component.

Kept in a module of its own (no FMPy, no numpy) so that a trace-writing worker process can raise and
report it without importing the FMI side.
"""

from __future__ import annotations


class ComponentError(RuntimeError):
    """A component failed; the message names the component, the time and the reason."""

    def __init__(self, component: str, time: float, reason: str) -> None:
        super().__init__(f"{component} failed at t = {time:.6g} s: {reason}")
        self.component, self.time, self.reason = component, time, reason

    def __reduce__(self):  # picklable with its three fields (a worker process sends it back)
        return (type(self), (self.component, self.time, self.reason))
