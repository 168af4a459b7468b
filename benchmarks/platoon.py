"""The benchmark platoon: 1 virtual target + N vehicles, sine law, the paper's start and wiring.

One definition for every engine, so that every master simulates the same system and the final
positions can be compared (``final_positions``).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from fmus.builders import DEFAULT_OUT

STEP = 0.01  # s, the paper's communication step
PAPER_START = {"radial_offset": 5.0, "heading_error": 0.1, "speed_factor": 0.8}
COUPLINGS = ("extrapolate", "hold")


def scenario_for(n: int, steps: int, coupling: str = "extrapolate"):
    """The platoon of ``orchestrator.scenario.scenario.build_scenario`` with ``n`` vehicles, Jacobi, ``steps`` steps."""
    from orchestrator.scenario.config import config_from_mapping
    from orchestrator.scenario.scenario import build_scenario

    config = config_from_mapping({
        "name": f"bench-{n}",
        "simulation": {"stop_time": steps * STEP, "step": STEP, "master": "jacobi", "coupling": coupling},
        "platoon": {"count": n, "law": "sine"},
        "initial": dict(PAPER_START),
    })
    return build_scenario(config)


def fmu_files(fmu_dir: Path = DEFAULT_OUT) -> dict[str, Path]:
    """Build the FMUs into ``fmu_dir`` when their sources changed (as ``platoon run`` does); their paths.
    A folder named ``native`` holds the native FMUs (orchestrator/components/kinds.py)."""
    from orchestrator.components.kinds import fmus_in_folder

    return fmus_in_folder(fmu_dir)


def unpacked_fmus(fmu_dir: Path = DEFAULT_OUT) -> dict[str, Any]:
    from orchestrator.components.fmu import UnpackedFmu

    return {name: UnpackedFmu.open(path) for name, path in fmu_files(fmu_dir).items()}


def final_positions(names: list[str], outputs: list[dict[str, float]]) -> dict[str, list[float]]:
    return {name: [values["x"], values["y"]] for name, values in zip(names, outputs)}


def causal_names(fmu: Any, causality: str) -> list[str]:
    return [v.name for v in fmu.description.modelVariables if v.causality == causality]


def routes_of(scenario, inputs: dict[str, list[str]], outputs: dict[str, list[str]]) -> list[list[tuple[int, int, int]]]:
    """Per component: (input index, source component index, output index), as Master builds them."""
    index = {spec.name: i for i, spec in enumerate(scenario.components)}
    routes: list[list[tuple[int, int, int]]] = [[] for _ in scenario.components]
    for c in scenario.connections:
        routes[index[c.destination]].append(
            (inputs[c.destination].index(c.input), index[c.source], outputs[c.source].index(c.output)))
    return routes
