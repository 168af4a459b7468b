"""Run a scenario end to end: build the FMUs if needed, wire, step, trace; or the monolithic reference.

Whatever happens, the trace keeps every step recorded so far and says how the run ended
(``platoon.run`` metadata: completed, failed with the component, time and reason, or interrupted).
"""

from __future__ import annotations

import json
import platform
import time as clock
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import fmpy
import pythonfmu

import fmus
from fmus.build import DEFAULT_OUT, build_fmus
from fmus.model.factory import target_stepper, vehicle_stepper
from fmus.model.platoon import PlatoonSystem

from . import __version__
from .components import ComponentError, FmuComponent, UnpackedFmu
from .config import Config
from .master import Master
from .scenario import Scenario, build_scenario, step_count
from .trace import TraceWriter

ENGINES = ("fmi", "monolithic")

Tick = Callable[[int], None]


@dataclass
class RunResult:
    trace: Path
    steps: int
    wall_time: float
    status: str  # "completed" | "failed" | "interrupted"
    error: str | None = None


def tool_versions() -> dict[str, str]:
    return {
        "platoon-cosim": __version__,
        "fmus": fmus.__version__,
        "fmpy": fmpy.__version__,
        "pythonfmu": pythonfmu.__version__,
        "python": platform.python_version(),
    }


def _descriptions(fmu: UnpackedFmu) -> dict[str, str]:
    return {
        v.name: f"{v.description} [{v.unit}]" if v.unit else v.description
        for v in fmu.description.modelVariables
        if v.causality == "output"
    }


def _open_fmus(fmu_dir: Path) -> dict[str, UnpackedFmu]:
    return {built.name: UnpackedFmu.open(built.path) for built in build_fmus(fmu_dir)}


def _monolithic_system(scenario: Scenario, fmus_by_kind: dict[str, UnpackedFmu]) -> PlatoonSystem:
    """The same steppers the FMUs would hold, from the same parameter values (FMU defaults + config)."""
    steppers = []
    for spec in scenario.components:
        values = {**fmus_by_kind[spec.fmu].start_values(), **spec.parameters}
        steppers.append(target_stepper(values, 0.0) if spec.fmu == "VirtualTarget" else vehicle_stepper(values, 0.0))
    return PlatoonSystem(steppers[0], steppers[1:])


def run_scenario(
    config: Config,
    config_text: str,
    out: Path,
    engine: str = "fmi",
    fmu_dir: Path = DEFAULT_OUT,
    tick: Tick | None = None,
) -> RunResult:
    """Run ``config`` with ``engine`` and write the trace to ``out``."""
    if engine not in ENGINES:
        raise ValueError(f"unknown engine {engine!r}; expected one of {', '.join(ENGINES)}")
    scenario = build_scenario(config)
    sim = config.simulation
    steps = step_count(sim.stop_time, sim.step)
    fmus_by_kind = _open_fmus(fmu_dir)
    started = clock.perf_counter()
    writer = None
    master = None
    status, error = "completed", None
    try:
        kinds = {spec.name: fmus_by_kind[spec.fmu] for spec in scenario.components}
        outputs = {
            spec.name: [v.name for v in kinds[spec.name].description.modelVariables if v.causality == "output"]
            for spec in scenario.components
        }
        writer = TraceWriter(
            out,
            [(spec.name, outputs[spec.name]) for spec in scenario.components],
            {name: _descriptions(fmu) for name, fmu in kinds.items()},
            every=sim.trace_every,
        )
        writer.metadata("platoon.config", {"toml": config_text, "resolved": config.model_dump_json()})
        writer.metadata("platoon.fmus", {kind: fmu.guid for kind, fmu in fmus_by_kind.items()})
        writer.metadata("platoon.tool", tool_versions())
        if engine == "fmi":
            components = [FmuComponent(spec.name, kinds[spec.name], spec.parameters) for spec in scenario.components]
            master = Master(components, scenario.connections, scenario.schedules, sim.master)
            master.run(sim.stop_time, sim.step, writer.record, steps, tick=tick)
        else:
            _run_monolithic(scenario, fmus_by_kind, outputs, writer, steps, tick)
    except ComponentError as failure:
        status, error = "failed", str(failure)
    except KeyboardInterrupt:
        status, error = "interrupted", "interrupted by the user"
    finally:
        if master is not None:
            master.close()
        if writer is not None:
            writer.metadata("platoon.run", {"status": status, "error": error or "", "engine": engine,
                                            "master": sim.master, "steps_recorded": writer.recorded + len(writer._rows)})
            writer.close()
        for fmu in fmus_by_kind.values():
            fmu.cleanup()
    return RunResult(Path(out), steps, clock.perf_counter() - started, status, error)


def _run_monolithic(
    scenario: Scenario,
    fmus_by_kind: dict[str, UnpackedFmu],
    outputs: dict[str, list[str]],
    writer: TraceWriter,
    steps: int,
    tick: Tick | None,
) -> None:
    sim = scenario.config.simulation
    system = _monolithic_system(scenario, fmus_by_kind)
    names = [spec.name for spec in scenario.components]
    order = [outputs[name] for name in names]
    vehicle_names = names[1:]

    def disturbances(t: float) -> list[tuple[float, float]]:
        values = {name: [0.0, 0.0] for name in vehicle_names}
        for schedule in scenario.schedules:
            slot = 0 if schedule.input.endswith("lateral_acceleration") else 1
            values[schedule.component][slot] += schedule.value_at(t)
        return [tuple(values[name]) for name in vehicle_names]

    def record(t: float, y: list[float]) -> None:
        rows = system.outputs(t, y)
        writer.record(t, [[row[key] for key in keys] for row, keys in zip(rows, order)])

    y = system.initial_state()
    t = 0.0
    try:
        system.set_disturbances(disturbances(t))
        record(t, y)
        for k in range(steps):
            t, t_next = k * sim.step, (k + 1) * sim.step
            system.set_disturbances(disturbances(t))
            y = system.advance(t, y, t_next - t, sim.max_substep)
            record(t_next, y)
            if tick is not None:
                tick(k + 1)
    except (ValueError, ZeroDivisionError, OverflowError) as failure:
        raise ComponentError("platoon (monolithic)", t, str(failure)) from None


def default_trace_path(config: Config, engine: str = "fmi") -> Path:
    stamp = clock.strftime("%Y%m%d-%H%M%S")
    suffix = "-monolithic" if engine == "monolithic" else ""
    return Path("runs") / f"{config.name}{suffix}-{stamp}.mcap"


def resolved_json(config: Config) -> str:
    return json.dumps(json.loads(config.model_dump_json()), indent=2)
