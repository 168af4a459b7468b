"""Cost per FMU-step of our engines and of the peers, on our own FMUs and wiring (issue 10).

The measurement code lives in ``orchestrator.bench`` (``engines.py`` lists the engines, ``steps.py``
the suite), shared with ``platoon bench steps``; this script keeps the original command line:

    .venv/bin/python benchmarks/bench_engines.py                       # all engines, N = 4, 16, 64; 3 rounds
    .venv/bin/python benchmarks/bench_engines.py --n 4 16 64 256 --rounds 5
    .venv/bin/python benchmarks/bench_engines.py --engines native slaves --n 64
    .venv/bin/python benchmarks/bench_engines.py --profile --n 4 16 64 # where the native engine's time goes

Writes runs/bench/engines-<time>.json (every sample, medians, ratios, versions, machine), or
runs/bench/profile-<time>.json with --profile.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from fmus.build import DEFAULT_OUT  # noqa: E402
from orchestrator.bench import profile, steps  # noqa: E402
from orchestrator.bench.common import DEFAULT_OUT_DIR, write_result  # noqa: E402
from orchestrator.bench import ENGINES  # noqa: E402


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--n", type=int, nargs="+", default=[4, 16, 64], help="vehicle counts (default 4 16 64)")
    parser.add_argument("--steps", type=int, default=1000, help="communication steps of 0.01 s (default 1000)")
    parser.add_argument("--rounds", type=int, default=3, help="interleaved repetitions (default 3)")
    parser.add_argument("--engines", nargs="+", default=list(ENGINES), choices=ENGINES)
    parser.add_argument("--out", type=Path, default=None, help="JSON results (default runs/bench/engines-<time>.json)")
    parser.add_argument("--profile", action="store_true",
                        help="instead: where the native engine's time goes (native vs floor in one process, "
                             "the floor's phases, perf by shared object), for each --n")
    args = parser.parse_args()
    fmu_dir = REPO / DEFAULT_OUT
    out_dir = REPO / DEFAULT_OUT_DIR

    def show(done: int, total: int, line: str) -> None:
        print(line, flush=True)

    if args.profile:
        result = profile.run(args.n, args.steps, args.rounds, fmu_dir, show)
        print(profile.markdown(result))
        suite = "profile"
    else:
        result = steps.run(args.engines, args.n, args.steps, args.rounds, fmu_dir, show)
        print()
        print(steps.markdown(result))
        suite = "engines"
    result["command"] = " ".join([Path(sys.executable).name, *sys.argv])
    print(f"results: {write_result(out_dir, suite, result, args.out)}")


if __name__ == "__main__":
    main()
