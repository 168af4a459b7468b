"""How big a run may be without ``--allow-long``: absurd sizes are refused before any work starts.

A valid config can still ask for a run that never ends on this machine (``simulation.stop_time =
1e12``, ``simulation.max_substep = 1e-12``). ``check_run_size`` refuses, with the numbers, a run above
any of these limits unless the user says ``--allow-long``. They sit well above every shipped config:

* ``MAX_STEPS``: communication steps (stop_time / step). The longest shipped run, the 100-vehicle
  hour of configs/bench/platoon100-1h.toml, takes 36 000; the paper's configs 10 000. A million steps
  of the paper's 4-vehicle platoon take about 100 s here (1e5 steps measured: 9.8 s) and record 1e6
  rows per component.
* ``MAX_SUBSTEPS_PER_STEP``: RK4 substeps per communication step (ceil(step / max_substep)); every
  shipped config uses 1. A thousand means max_substep = 10 µs at the default 0.01 s step.
* ``MAX_FMU_SUBSTEPS``: the run's work, counted over every component the wiring makes: steps x
  (substeps per step x (vehicles + target) + link FMUs). A link FMU does not integrate (one step per
  communication step whatever max_substep says), but its step costs about what a vehicle's does (1.2-1.5
  times, docs/config.md): with [links] every vehicle has two more FMUs and a run takes 3-4x as long. It
  counts as one FMU-substep. The 100-vehicle hour is 3.6e6 and took 229 s (64 µs per
  FMU-step; the paper's platoon 20 µs), so 1e8 takes between half an hour and two hours here.

Above 2**53 substeps per FMU nothing runs, flag or not (the config itself refuses: step counts are
no longer exact in double precision).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

from fmus.model.integrate import substep_count

from orchestrator.scenario.raw_config import ConfigError
from orchestrator.scenario.wiring import component_names

if TYPE_CHECKING:
    from orchestrator.scenario.config import Config

MAX_STEPS = 1_000_000
MAX_SUBSTEPS_PER_STEP = 1_000
MAX_FMU_SUBSTEPS = 100_000_000
ALLOW_LONG = "--allow-long"

# analyze linearizes the whole platoon: 4 N states, a 4N x 4N Jacobian by central differences (8 N
# right-hand sides of N vehicles each) and its eigenvalues. Measured here: N = 50 3.4 s, N = 100 11 s,
# growing as N^3. The eigenvalue families do not depend on N (docs/model.md).
MAX_ANALYZE_VEHICLES = 100


@dataclass(frozen=True)
class RunSize:
    """How big a run of a config is: what the limits compare, and what the refusal says was counted."""

    steps: int  # communication steps
    per_step: int  # RK4 substeps per communication step of an integrating FMU (vehicle, target)
    integrating: int  # FMUs that integrate: the vehicles (live ones included) and the virtual target
    links: int  # link FMUs (one step per communication step)

    @property
    def work(self) -> int:
        """FMU-substeps: every component's steps, an integrating one's substeps each."""
        return self.steps * (self.per_step * self.integrating + self.links)

    def counted(self) -> str:
        """What was counted, as the refusal says it (every component the wiring makes, links apart)."""
        integrating = (f"{self.per_step:,} substeps x {self.integrating:,} components "
                       f"({self.integrating - 1:,} vehicles and the target)")
        if not self.links:
            return f"{self.steps:,} steps x {integrating}"
        return f"{self.steps:,} steps x ({integrating} + {self.links:,} link FMUs, one step each)"


def run_size(config: Config) -> RunSize:
    """The size of a run of ``config``, counting every component its wiring makes (scenario/wiring.py)."""
    sim = config.simulation
    linked = frozenset(config.linked())
    components = component_names(config.platoon.count, linked)
    return RunSize(config.steps, substep_count(sim.step, sim.max_substep), len(components) - len(linked), len(linked))


def check_run_size(config: Config) -> None:
    """Raise ``ConfigError`` naming the number and the limit when a run of ``config`` is absurdly big."""
    size = run_size(config)
    steps, per_step, work = size.steps, size.per_step, size.work
    if steps > MAX_STEPS:
        raise ConfigError(f"simulation.stop_time / simulation.step = {steps:,} steps: more than {MAX_STEPS:,} "
                          f"(a run this long needs {ALLOW_LONG})")
    if per_step > MAX_SUBSTEPS_PER_STEP:
        raise ConfigError(f"simulation.step / simulation.max_substep = {per_step:,} RK4 substeps per step: more than "
                          f"{MAX_SUBSTEPS_PER_STEP:,} (a run this fine needs {ALLOW_LONG})")
    if work > MAX_FMU_SUBSTEPS:
        raise ConfigError(f"{size.counted()} = {work:,} FMU-substeps: more than {MAX_FMU_SUBSTEPS:,} (hours of "
                          f"work; a run this big needs {ALLOW_LONG})")


def check_analyze_size(config: Config) -> None:
    """Raise ``ConfigError`` when ``platoon analyze`` would linearize more vehicles than ``MAX_ANALYZE_VEHICLES``."""
    if config.platoon.count > MAX_ANALYZE_VEHICLES:
        raise ConfigError(f"platoon.count = {config.platoon.count}: analyze linearizes at most {MAX_ANALYZE_VEHICLES} "
                          f"vehicles ({4 * config.platoon.count:,} states; the time grows as N^3 and the eigenvalue "
                          f"families do not depend on N: try --set platoon.count=10, or {ALLOW_LONG})")
