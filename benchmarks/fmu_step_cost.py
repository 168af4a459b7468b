"""Cost of one doStep of each FMU under FMPy, alone (inputs held at their start values).

    python -m benchmarks.fmu_step_cost [--steps 5000] [--repeat 5]

Prints the median over repetitions of the µs per doStep (plus a setReal of all inputs and a getReal
of all outputs, as a master does each step), for each FMU and coupling mode, and, as the reference
measured in the same run, the cost of the same slave's stepper called directly without FMI. The FMUs
are built (when their sources changed) into build/fmus under the current folder, as ``platoon run`` does.
"""

from __future__ import annotations

import argparse
import statistics
import time

from fmus.model.factory import target_stepper, vehicle_stepper
from orchestrator.components.fmu import FmuComponent, UnpackedFmu

from .platoon import unpacked_fmus


def fmu_cost(fmu: UnpackedFmu, coupling: str, steps: int) -> float:
    component = FmuComponent("bench", fmu, {"coupling": coupling})
    component.initialize(0.0)
    inputs = list(component.input_defaults)
    component.set_inputs(inputs)
    component.end_initialization()
    h = 0.01
    started = time.perf_counter()
    for k in range(steps):
        component.set_inputs(inputs)
        component.step(k * h, h)
        component.get_outputs()
    elapsed = time.perf_counter() - started
    component.close()
    return elapsed / steps * 1e6


def direct_cost(fmu: UnpackedFmu, coupling: str, steps: int) -> float:
    values = {**fmu.start_values(), "coupling": coupling}
    make = vehicle_stepper if fmu.description.coSimulation.modelIdentifier == "Vehicle" else target_stepper
    stepper = make(values, 0.0)
    h = 0.01
    started = time.perf_counter()
    for k in range(steps):
        stepper.step(k * h, h)
        stepper.outputs()
    return (time.perf_counter() - started) / steps * 1e6


def main() -> None:
    parser = argparse.ArgumentParser(prog="python -m benchmarks.fmu_step_cost",
                                     description=__doc__.splitlines()[0])
    parser.add_argument("--steps", type=int, default=5000)
    parser.add_argument("--repeat", type=int, default=5)
    args = parser.parse_args()
    fmus = unpacked_fmus()
    print(f"{'FMU':14s} {'coupling':12s} {'FMPy µs/step':>13s} {'direct µs/step':>15s} {'ratio':>6s}")
    for name, fmu in fmus.items():
        for coupling in ("extrapolate", "hold"):
            through_fmi, direct = [], []
            for _ in range(args.repeat):  # interleaved, so drift affects both alike
                through_fmi.append(fmu_cost(fmu, coupling, args.steps))
                direct.append(direct_cost(fmu, coupling, args.steps))
            a, b = statistics.median(through_fmi), statistics.median(direct)
            print(f"{name:14s} {coupling:12s} {a:13.1f} {b:15.1f} {a / b:6.2f}")
    for fmu in fmus.values():
        fmu.cleanup()


if __name__ == "__main__":
    main()
