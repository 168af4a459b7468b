"""Will this `platoon run` want a trace writer process? Answered from the config's raw TOML, before
pydantic and the config models load, so the worker can start first and be ready by the first step.

The worker's start-up (an interpreter, the MCAP writer, zstd; about 0.1 s of one core) used to begin
only once the config was validated, which made it finish after the run's first step: the stepping
process filled the pipe and waited. Started with the command, it loads on the second core while this
process loads pydantic and the models (docs/performance.md, "Start-up"). The forecast reads only the
keys that size the recording (simulation.stop_time, step, trace_every, platoon.count, ``--set`` and
``--trace-every`` applied); the run itself decides as always (``choose_trace_writer`` on the validated
config) and takes the early worker only if it decided the same. A wrong forecast costs time, never
correctness: an unneeded worker is ended (``discard_prestarted``), a missing one started as before.
"""

from __future__ import annotations

from typing import Any

from orchestrator.cli.options import RunOptions
from orchestrator.scenario.raw_config import (DEFAULT_COUNT, DEFAULT_STEP, DEFAULT_STOP_TIME, DEFAULT_TRACE_EVERY,
                                              apply_override, read_config_text, recorded_rows, step_count)


def wants_trace_worker(options: RunOptions) -> bool:
    """True when the run these options describe will most likely write its trace in a worker process."""
    if options.trace_writer == "inline":
        return False
    try:
        rows, components = _recording_size(options)
    except Exception:  # an unreadable or odd config: the run reports it; no worker wasted on it
        return False
    from orchestrator.observers.trace import choose_trace_writer

    try:
        return choose_trace_writer(options.trace_writer or "auto", rows, components) == "process"
    except ValueError:  # an unknown --trace-writer: the run refuses it
        return False


def _recording_size(options: RunOptions) -> tuple[int, int]:
    """(rows recorded, components at least) of the run, from the raw config with its overrides."""
    import tomllib

    raw: dict[str, Any] = tomllib.loads(read_config_text(options.config))
    for assignment in options.overrides:
        apply_override(raw, assignment)
    simulation, platoon = raw.get("simulation", {}), raw.get("platoon", {})
    steps = step_count(float(simulation.get("stop_time", DEFAULT_STOP_TIME)), float(simulation.get("step", DEFAULT_STEP)))
    every = options.trace_every or int(simulation.get("trace_every", DEFAULT_TRACE_EVERY))
    return recorded_rows(steps, every), int(platoon.get("count", DEFAULT_COUNT)) + 1  # the vehicles and the target
