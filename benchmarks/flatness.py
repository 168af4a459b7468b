"""Why the cost per FMU-step grows with N (issue 10's flatness floor); code in orchestrator/bench/flatness.py.

    python benchmarks/flatness.py orders --n 4 16 64 256              # floor: Master's order vs per component, idle instances
    python benchmarks/flatness.py callgrind --n 4 16 64 256           # instructions and simulated misses, native stepping
    python benchmarks/flatness.py callgrind --engine native python fmpy-bare  # ... and the master's own share, by engine
    python benchmarks/flatness.py callgrind --core phases=/tmp/a.so --core per-component=/tmp/b.so
    python benchmarks/flatness.py cores phases=/tmp/a.so per-component=/tmp/b.so --n 4 16 64 256 --rounds 5

``cores`` and ``--core`` compare builds of orchestrator/native/_core.c (copy the built
``orchestrator/native/_core.*.so`` aside before rebuilding): the native engine with each build,
interleaved in fresh interpreters. Every command writes runs/bench/flatness-<what>-<time>.json.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from fmus.build import DEFAULT_OUT  # noqa: E402
from orchestrator.bench import flatness  # noqa: E402
from orchestrator.bench.common import DEFAULT_OUT_DIR, write_result  # noqa: E402


def labelled(items: list[str]) -> dict[str, str]:
    cores = {}
    for item in items:
        label, _, path = item.partition("=")
        if not path or not Path(path).is_file():
            raise SystemExit(f"expected LABEL=PATH to a built _core .so, got {item!r}")
        cores[label] = str(Path(path).resolve())
    return cores


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0],
                                     formatter_class=argparse.RawDescriptionHelpFormatter, epilog=__doc__)
    parser.add_argument("what", choices=("orders", "callgrind", "cores"))
    parser.add_argument("cores", nargs="*", help="cores: LABEL=PATH of each _core build")
    parser.add_argument("--n", type=int, nargs="+", default=list(flatness.DEFAULT_N))
    parser.add_argument("--steps", type=int, default=None, help="steps per sample (orders 150, cores 1000)")
    parser.add_argument("--rounds", type=int, default=5)
    parser.add_argument("--repeats", type=int, default=3, help="orders: processes per N")
    parser.add_argument("--core", action="append", default=[], help="callgrind: LABEL=PATH (default: the installed core)")
    parser.add_argument("--ll", choices=("l2", "detected", "both"), default="l2",
                        help="callgrind's last-level cache: this machine's L2 (512 KiB), valgrind's detected L3, or both")
    parser.add_argument("--fmu-steps", type=int, default=2500, help="callgrind: FMU-steps per measurement")
    parser.add_argument("--engine", nargs="+", choices=("native", "python", "fmpy-bare"), default=["native"],
                        help="callgrind: the engines to measure")
    args = parser.parse_args()
    fmu_dir = REPO / DEFAULT_OUT

    def show(done: int, total: int, line: str) -> None:
        print(line, flush=True)

    if args.what == "orders":
        result = flatness.run(args.n, args.steps or 150, args.rounds, args.repeats, fmu_dir, show)
        text = flatness.markdown(result)
    elif args.what == "callgrind":
        levels = {"l2": [flatness.L2], "detected": [None], "both": [flatness.L2, None]}[args.ll]
        result = flatness.callgrind_series(args.n, args.fmu_steps, levels, labelled(args.core) or None, fmu_dir, show,
                                           args.engine)
        text = flatness.callgrind_markdown(result)
    else:
        if len(args.cores) < 2:
            raise SystemExit("cores: give at least two LABEL=PATH")
        result = flatness.compare_cores(labelled(args.cores), args.n, args.steps or 1000, args.rounds, fmu_dir, show)
        text = flatness.cores_markdown(result)
    print()
    print(text)
    result["command"] = " ".join([Path(sys.executable).name, *sys.argv])
    print(f"results: {write_result(REPO / DEFAULT_OUT_DIR, f'flatness-{args.what}', result)}")


if __name__ == "__main__":
    main()
