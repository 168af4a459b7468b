"""The one interface every engine implements, what it is built from, and how a name finds it.

An engine steps a scenario's components and hands what they output to the run's observers
(orchestrator/observers/base.py): ``start`` initializes them (the initial point included),
``advance`` runs the steps, ``close`` releases them whatever happened. Between two steps it calls
``check()``, which raises to stop the run there (Ctrl-C), never inside a component call.

Engines live in ``orchestrator.execution.engines``, one module each, whose ``Engine`` class is the
implementation: adding an engine is adding one file there. Today: ``python`` (the master loop in
Python over FMPy or live robots), ``native`` (the same loop in C over the native core) and
``monolithic`` (no FMUs: the whole platoon as one system, the accuracy reference).
"""

from __future__ import annotations

import pkgutil
from dataclasses import dataclass, field
from importlib import import_module
from typing import TYPE_CHECKING, Callable, ClassVar, Protocol

if TYPE_CHECKING:
    from orchestrator.components.fmu import UnpackedFmu
    from orchestrator.observers.base import Observers
    from orchestrator.scenario.config import Config
    from orchestrator.scenario.scenario import Scenario

Check = Callable[[], None]


@dataclass
class EngineSetup:
    """What an engine is built from: the scenario, its opened FMUs and how the run records."""

    config: "Config"
    scenario: "Scenario"
    fmus: dict[str, "UnpackedFmu"]  # by FMU name (Vehicle, VirtualTarget ...)
    outputs: dict[str, list[str]]  # component name -> its output names, in the FMU's order
    block: int  # rows per block handed to the observers (engines that fill blocks)
    live: set[str] = field(default_factory=set)  # the components that are live robots

    def fmu_of(self, component: str) -> "UnpackedFmu":
        return self.fmus[next(spec.fmu for spec in self.scenario.components if spec.name == component)]


class Engine(Protocol):
    """Steps the components of one run; see the module's docstring."""

    name: ClassVar[str]
    time: float  # the communication point reached

    def start(self, observers: "Observers", check: Check) -> None:
        """Instantiate and initialize the components; the observers get the initial point (or it opens
        the first block)."""

    def advance(self, steps: int, observers: "Observers", check: Check) -> None:
        """Run ``steps`` communication steps, handing every point (or block of points) to ``observers``
        and ``observers.advanced(k)`` as steps complete; ``check()`` between two steps."""

    def close(self) -> None:
        """Free the components (called once, whatever happened)."""


def engine_names() -> tuple[str, ...]:
    """The engines there are: the modules of ``orchestrator.execution.engines``."""
    from orchestrator.execution import engines

    return tuple(sorted(module.name for module in pkgutil.iter_modules(engines.__path__)))


def engine_class(name: str) -> type:
    """The ``Engine`` of the engine called ``name``; ValueError naming the known ones otherwise."""
    names = engine_names()
    if name not in names:
        raise ValueError(f"unknown engine {name!r}; expected one of {', '.join(names)}")
    return import_module(f"orchestrator.execution.engines.{name}").Engine


def default_engine(config: "Config | None" = None) -> str:
    """The native engine when its extension is built (bit-identical results), else the Python one; the
    Python one for a config with a live or remote vehicle (the native core steps local FMUs only)."""
    if config is not None and (config.live_vehicles() or config.remote_vehicles()):
        return "python"
    from orchestrator.execution.native import available

    return "native" if available() else "python"
