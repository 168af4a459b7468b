"""Measure the coupling error table of docs/coupling.md.

For each paper scenario (platoon, m3pi), law (sine, regular), coupling mode (hold, extrapolate) and
communication step h, run the FMU co-simulation and the monolithic reference of the same config and
print the largest position, gap and speed deviation over the whole run, as a Markdown table.

    python -m benchmarks.coupling_accuracy [--master jacobi|gauss-seidel]

Run it from the repository: it reads configs/paper/platoon.toml and m3pi.toml.

Each FMU and the reference take one RK4 substep per communication step (max_substep = h), so the
table isolates the coupling. Takes several minutes (the h = 0.005 s runs dominate).
"""

from __future__ import annotations

import argparse
import time

from orchestrator.analysis.accuracy import coupling_error
from orchestrator.scenario.config import load_config

from .common import PAPER_CONFIGS

STEPS = (0.02, 0.01, 0.005)


def main() -> None:
    parser = argparse.ArgumentParser(prog="python -m benchmarks.coupling_accuracy",
                                     description=__doc__.splitlines()[0])
    parser.add_argument("--master", default="jacobi", choices=("jacobi", "gauss-seidel"))
    args = parser.parse_args()
    print(f"master: {args.master}; largest deviation from the monolithic run over the whole run")
    print("| scenario | law | coupling | " + " | ".join(f"h = {h} s" for h in STEPS) + " | ratios |")
    print("|---|---|---|" + "---|" * len(STEPS) + "---|")
    started = time.perf_counter()
    for scenario in ("platoon", "m3pi"):
        for law in ("sine", "regular"):
            config, _ = load_config(PAPER_CONFIGS / f"{scenario}.toml", [f"platoon.law={law}"])
            for coupling in ("hold", "extrapolate"):
                errors = [coupling_error(config, h, master=args.master, coupling=coupling) for h in STEPS]
                cells = [f"{e.position:.3g} m (gap {e.gap:.2g}, speed {e.speed:.2g})" for e in errors]
                ratios = ", ".join(f"{a.position / b.position:.2f}" for a, b in zip(errors, errors[1:]))
                print(f"| {scenario} ({config.simulation.stop_time:g} s) | {law} | {coupling} | " + " | ".join(cells) + f" | {ratios} |", flush=True)
    print(f"(measured in {time.perf_counter() - started:.0f} s)")


if __name__ == "__main__":
    main()
