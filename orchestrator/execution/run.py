"""Run a scenario end to end: ``run_scenario`` builds an ``Execution`` (orchestrator/execution/execution.py)
and runs it; plus what a run's caller needs around it (the default trace path, the tool versions).

Whatever happens, the trace keeps every step recorded so far and says how the run ended
(``platoon.run`` metadata: completed, failed with the component, time and reason, or interrupted).
"""

from __future__ import annotations

import json
import time as clock
from pathlib import Path
from typing import TYPE_CHECKING

from fmus.builders import DEFAULT_OUT
from orchestrator.execution.engine import default_engine, engine_names
from orchestrator.execution.execution import Execution, RunResult, Tick
from orchestrator.observers.trace import TRACE_WRITERS, WORKER_MESSAGES, choose_trace_writer, open_trace_writer
from orchestrator.support.versions import tool_versions
from orchestrator.trace.foxglove import SCENE_RATE
from orchestrator.trace.output import Claim, claim_new

if TYPE_CHECKING:
    from orchestrator.scenario.config import Config
    from orchestrator.observers.foxglove_view import FoxgloveView

__all__ = ["ENGINES", "TRACE_WRITERS", "WORKER_MESSAGES", "RunResult", "choose_trace_writer", "default_engine",
           "default_trace_path", "open_trace_writer", "resolved_json", "run_scenario", "tool_versions"]

# "native": the compiled stepping core (orchestrator/execution/native); "python": the same master in Python on
# FMPy; "monolithic": the whole platoon as one system, no FMUs stepped (the accuracy reference).
ENGINES = engine_names()



def run_scenario(
    config: Config,
    config_text: str,
    out: Path | Claim | None,
    engine: str | None = None,
    fmu_dir: Path = DEFAULT_OUT,
    tick: Tick | None = None,
    foxglove: bool = True,
    scene_rate: float = SCENE_RATE,
    trace_writer: str = "auto",
    summarize: bool = False,
    live_view: "FoxgloveView | None" = None,
) -> RunResult:
    """Run ``config`` with ``engine`` and write the trace to ``out`` (``None``: record nothing).

    ``out`` is a path (claimed here: ``orchestrator.trace.output.claim``, which raises ``OutputError``
    for a path in use by another run or holding a file that is not a trace) or a ``Claim`` made by
    the caller. The trace is written aside (``<out>.partial``) and put in place once finalized;
    ``RunResult.trace`` is where the data ended up.

    ``foxglove`` adds the Foxglove channels (scene at ``scene_rate`` Hz of simulated time, errors,
    transforms, log). SIGINT and SIGTERM stop the run at the next communication point with status
    "interrupted"; the trace is finalized with every point recorded up to there. ``trace_writer``:
    where the trace is encoded (``TRACE_WRITERS``); both give the same file. ``summarize``: accumulate
    the per-vehicle summary of the recorded rows while stepping (``RunResult.summary``), so printing it
    needs no second read of the trace. ``live_view``: a started ``FoxgloveView`` (orchestrator/observers/foxglove_view.py)
    that shows what the trace records, the run paced as it says; the caller closes it.
    """
    return Execution(config, config_text, out, engine, fmu_dir, tick, foxglove, scene_rate, trace_writer, summarize,
                     live_view).run()


def default_trace_path(config: Config, engine: str | None = None) -> Claim:
    """Claim a fresh ``runs/<name>[-monolithic]-<time>.mcap`` (``-2``, ``-3`` ... when two runs of one
    config start in the same second): never a path another run or an existing file uses."""
    stamp = clock.strftime("%Y%m%d-%H%M%S")
    suffix = "-monolithic" if engine == "monolithic" else ""
    return claim_new(Path("runs"), f"{config.name}{suffix}-{stamp}")


def resolved_json(config: Config) -> str:
    return json.dumps(json.loads(config.model_dump_json()), indent=2)
