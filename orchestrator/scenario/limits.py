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
* ``MAX_FMU_SUBSTEPS``: the run's work, steps x substeps per step x components (vehicles + target).
  The 100-vehicle hour is 3.6e6 and took 229 s (64 µs per FMU-step; the paper's platoon 20 µs), so
  1e8 takes between half an hour and two hours here.

Above 2**53 substeps per FMU nothing runs, flag or not (the config itself refuses: step counts are
no longer exact in double precision).
"""

from __future__ import annotations

from fmus.model.integrate import substep_count

from orchestrator.scenario.config import Config, ConfigError

MAX_STEPS = 1_000_000
MAX_SUBSTEPS_PER_STEP = 1_000
MAX_FMU_SUBSTEPS = 100_000_000
ALLOW_LONG = "--allow-long"

# analyze linearizes the whole platoon: 4 N states, a 4N x 4N Jacobian by central differences (8 N
# right-hand sides of N vehicles each) and its eigenvalues. Measured here: N = 50 3.4 s, N = 100 11 s,
# growing as N^3. The eigenvalue families do not depend on N (docs/model.md).
MAX_ANALYZE_VEHICLES = 100


def run_size(config: Config) -> tuple[int, int, int]:
    """(steps, RK4 substeps per step, FMU-substeps) of a run of ``config``."""
    sim = config.simulation
    steps = config.steps
    per_step = substep_count(sim.step, sim.max_substep)
    return steps, per_step, steps * per_step * (config.platoon.count + 1)


def check_run_size(config: Config) -> None:
    """Raise ``ConfigError`` naming the number and the limit when a run of ``config`` is absurdly big."""
    steps, per_step, work = run_size(config)
    if steps > MAX_STEPS:
        raise ConfigError(f"simulation.stop_time / simulation.step = {steps:,} steps: more than {MAX_STEPS:,} "
                          f"(a run this long needs {ALLOW_LONG})")
    if per_step > MAX_SUBSTEPS_PER_STEP:
        raise ConfigError(f"simulation.step / simulation.max_substep = {per_step:,} RK4 substeps per step: more than "
                          f"{MAX_SUBSTEPS_PER_STEP:,} (a run this fine needs {ALLOW_LONG})")
    if work > MAX_FMU_SUBSTEPS:
        raise ConfigError(f"{steps:,} steps x {per_step:,} substeps x {config.platoon.count + 1:,} components = {work:,} "
                          f"FMU-substeps: more than {MAX_FMU_SUBSTEPS:,} (hours of work; a run this big needs "
                          f"{ALLOW_LONG})")


def check_analyze_size(config: Config) -> None:
    """Raise ``ConfigError`` when ``platoon analyze`` would linearize more vehicles than ``MAX_ANALYZE_VEHICLES``."""
    if config.platoon.count > MAX_ANALYZE_VEHICLES:
        raise ConfigError(f"platoon.count = {config.platoon.count}: analyze linearizes at most {MAX_ANALYZE_VEHICLES} "
                          f"vehicles ({4 * config.platoon.count:,} states; the time grows as N^3 and the eigenvalue "
                          f"families do not depend on N: try --set platoon.count=10, or {ALLOW_LONG})")
