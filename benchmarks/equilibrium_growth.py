"""How far a platoon started on its equilibrium strays from it, over time and along the platoon.

    platoon run configs/paper/platoon.toml --set platoon.count=100 --set path.radius=2000.0 \\
        --set initial.radial_offset=0.0 --set initial.heading_error=0.0 --set initial.speed_factor=1.0 \\
        --set simulation.step=0.1 --set simulation.max_substep=0.1 --set simulation.stop_time=400 \\
        --trace-every 10 --out runs/long.mcap
    python -m benchmarks.equilibrium_growth runs/long.mcap

For each trace: how the run ended, then at a few simulated times the largest |V - V_c|, |d - d*| and
|path error| seen so far over every vehicle (and the vehicle with the largest speed deviation), and
the largest |V - V_c| so far at the last vehicle, at 3/4, 1/2 and 1/4 of the platoon and at vehicle 1.
Started on the equilibrium, nothing but rounding and the integrator's truncation error perturbs the
platoon, so these columns show how that seed grows along the speed chain (docs/model.md, section 10).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

from orchestrator.scenario.config import Config, config_from_mapping
from orchestrator.analysis.metrics import path_errors
from orchestrator.trace import Trace, load

TIMES = (1, 10, 25, 50, 100, 150, 200, 300, 400, 600, 800, 1000, 1800, 2700, 3600)


def deviations(trace: Trace, config: Config) -> tuple[list[str], np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The vehicles' names, the recorded times, and |V - V_c|, |d - d*| and |path error| at every
    recorded point (one row per vehicle): how far each vehicle is from the circular equilibrium.

    Shared with ``trace_memory``, which checks with them that its long run stayed a platoon.
    """
    names = trace.vehicles()
    components = [trace.component(name) for name in names]
    speed = np.array([np.abs(c["speed"] - config.platoon.speed) for c in components])
    gap = np.array([np.abs(c["gap"] - config.platoon.d_star) for c in components])
    offset = np.array([np.abs(path_errors(config, c["x"], c["y"])) for c in components])
    return names, components[0]["t"], speed, gap, offset


def growth_table(path: Path) -> str:
    """The table described in the module docstring, for one trace."""
    trace = load(path)
    if trace.config is None:
        raise SystemExit(f"{path}: no platoon.config metadata (not written by platoon run?)")
    config = config_from_mapping(trace.config)
    names, t, speed, gap, offset = deviations(trace, config)
    n = len(names)
    # running maxima along time, per vehicle
    speed, gap, offset = (np.maximum.accumulate(a, axis=1) for a in (speed, gap, offset))
    picks = sorted({n, 3 * n // 4, n // 2, n // 4, 1}, reverse=True)
    run = trace.run
    lines = [f"{path}: {n} vehicles, status {run.get('status', '?')}" + (f": {run['error']}" if run.get("error") else ""),
             f"{'t [s]':>8} {'max|V-Vc|':>10} {'vehicle':>10} {'max|d-d*|':>10} {'max|path|':>10}   "
             + " ".join(f"{'v' + str(i):>8}" for i in picks)]
    for when in [x for x in TIMES if x < t[-1]] + [t[-1]]:
        k = min(int(np.searchsorted(t, when - 1e-9)), len(t) - 1)
        column = speed[:, k]
        lines.append(f"{t[k]:8.1f} {column.max():10.2e} {names[int(column.argmax())]:>10} {gap[:, k].max():10.2e} "
                     f"{offset[:, k].max():10.2e}   " + " ".join(f"{column[i - 1]:8.1e}" for i in picks))
    return "\n".join(lines)


def main() -> int:
    parser = argparse.ArgumentParser(prog="python -m benchmarks.equilibrium_growth", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("traces", type=Path, nargs="+", help="traces written by platoon run")
    paths = parser.parse_args().traces
    missing = [str(path) for path in paths if not path.is_file()]
    if missing:
        parser.error(f"no such trace: {', '.join(missing)}")
    for path in paths:
        print(growth_table(path))
        print()
    return 0


if __name__ == "__main__":
    sys.exit(main())
