"""The link's states, modelled on the Distributed Co-simulation Protocol (DCP): a table of allowed
transitions, checked before any change, and every change announced with its reason.

* configured:   session open, waiting for the other side (its liveliness token, its first pose)
* synchronized: the other side is there and its data is valid; no step taken yet
* running:      commands flow every step
* stopped:      ended on purpose (run finished, Ctrl-C, a watchdog stopped the wheels); a robot
                side may go back to running when valid commands come again, or be reset to
                configured for a new host
* error:        ended by a fault (robot lost, no pose in time); only stopping is left
"""

from __future__ import annotations

from enum import Enum
from typing import Callable


class LinkState(Enum):
    CONFIGURED = "configured"
    SYNCHRONIZED = "synchronized"
    RUNNING = "running"
    STOPPED = "stopped"
    ERROR = "error"


ALLOWED: dict[LinkState, frozenset[LinkState]] = {
    LinkState.CONFIGURED: frozenset({LinkState.SYNCHRONIZED, LinkState.RUNNING, LinkState.STOPPED, LinkState.ERROR}),
    LinkState.SYNCHRONIZED: frozenset({LinkState.RUNNING, LinkState.STOPPED, LinkState.ERROR}),
    LinkState.RUNNING: frozenset({LinkState.STOPPED, LinkState.ERROR}),
    LinkState.STOPPED: frozenset({LinkState.RUNNING, LinkState.CONFIGURED, LinkState.ERROR}),
    LinkState.ERROR: frozenset({LinkState.STOPPED}),
}


class StateError(RuntimeError):
    """A transition the table does not allow (a bug in the caller, named with both states)."""


class StateMachine:
    """Current state of one link; ``announce(old, new, reason)`` hears of every change."""

    def __init__(self, who: str, announce: Callable[[LinkState, LinkState, str], None]) -> None:
        self.who = who
        self.state = LinkState.CONFIGURED
        self._announce = announce

    def go(self, new: LinkState, reason: str) -> None:
        old = self.state
        if new == old:
            return
        if new not in ALLOWED[old]:
            raise StateError(f"{self.who}: {old.value} -> {new.value} is not allowed ({reason})")
        self.state = new
        self._announce(old, new, reason)
