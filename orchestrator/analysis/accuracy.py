"""Coupling accuracy: a co-simulation measured against the monolithic reference of the same config.

Used by the tests of coupling order and by ``python -m benchmarks.coupling_accuracy``, which prints
the table in docs/coupling.md.
"""

from __future__ import annotations

import tempfile
from pathlib import Path

from orchestrator.analysis.compare import Deviation, deviations
from orchestrator.scenario.config import Config
from orchestrator.execution.run import run_scenario
from orchestrator.trace import Trace, load


def with_settings(config: Config, **simulation) -> Config:
    """The config with [simulation] keys replaced (validated like any config)."""
    from orchestrator.scenario.config import config_from_mapping

    raw = config.model_dump()
    raw["simulation"].update(simulation)
    return config_from_mapping(raw)


def run_both(config: Config, fmu_dir: Path | None = None) -> tuple[Trace, Trace]:
    """(co-simulation, monolithic) traces of ``config``."""
    kwargs = {} if fmu_dir is None else {"fmu_dir": fmu_dir}
    with tempfile.TemporaryDirectory(prefix="platoon-accuracy-") as scratch:
        traces = []
        for engine in (None, "monolithic"):  # the default FMU engine, then the reference
            result = run_scenario(config, "", Path(scratch) / f"{engine or 'fmus'}.mcap", engine=engine, **kwargs)
            if result.status != "completed":
                raise RuntimeError(f"{engine} run {result.status}: {result.error}")
            traces.append(load(result.trace))
    return traces[0], traces[1]


def coupling_error(config: Config, step: float, fmu_dir: Path | None = None, **simulation) -> Deviation:
    """Largest deviation of the co-simulation from the monolithic run at communication step ``step``.

    Each FMU (and the monolithic reference) takes one RK4 substep per communication step, so the two
    integrate identically and only the coupling differs.
    """
    config = with_settings(config, step=step, max_substep=step, **simulation)
    cosim, reference = run_both(config, fmu_dir)
    return deviations(cosim, reference)
