"""Run every paper scenario (configs/paper/*.toml) with both laws: summaries, peaks and wall times.

    python -m benchmarks.paper_scenarios [--json runs/bench/paper_scenarios.json]

The numbers in docs/reproduction.md come from this benchmark. Wall time is the whole run_scenario call
(FMUs already built): instantiation, initialization, stepping and trace writing. Run it from the
repository: it runs configs/paper/*.toml (``scenarios.find_configs``, as ``platoon bench scenarios``)
with the FMUs in build/fmus.
"""

from __future__ import annotations

import argparse
import tempfile
from pathlib import Path

from fmus.builders import DEFAULT_OUT
from orchestrator.analysis.metrics import report_json, summarize
from orchestrator.analysis.validity import departures_of_trace
from orchestrator.support.output import OutputError
from orchestrator.trace import load

from .common import DEFAULT_OUT_DIR, BenchError, check_json_target, write_json
from .scenarios import find_configs, run_config


def main() -> None:
    parser = argparse.ArgumentParser(prog="python -m benchmarks.paper_scenarios",
                                     description=__doc__.splitlines()[0])
    parser.add_argument("--json", type=Path, default=DEFAULT_OUT_DIR / "paper_scenarios.json")
    args = parser.parse_args()
    try:
        check_json_target(args.json)  # before minutes of runs, not after them
        paths = find_configs(None)
    except (BenchError, OutputError) as error:
        raise SystemExit(f"error: {error}") from None
    results = []
    with tempfile.TemporaryDirectory() as scratch:
        for path in paths:
            for law in ("sine", "regular"):
                out = Path(scratch) / f"{path.stem}-{law}.mcap"
                config, result = run_config(path, None, out, [f"platoon.law={law}"], DEFAULT_OUT)
                trace = load(out)
                summary = report_json(summarize(trace, config), config, departures_of_trace(trace, config))
                record = {"scenario": path.stem, "law": law, "wall_time_s": round(result.wall_time, 3),
                          "steps": result.steps, "trace_bytes": out.stat().st_size, **summary}
                results.append(record)
                print(f"{path.stem:24s} {law:8s} {result.wall_time:6.2f} s  " + "  ".join(
                    f"{v['name']}: off {v['path_offset']:+.3g} gap {v['gap']:.5g} V {v['speed']:.5g} max|e| {v['path_error_max']:.3g}"
                    for v in summary["vehicles"]), flush=True)
    try:
        print(f"wrote {write_json(args.json, results, indent=2)}")  # the output rule: aside, synced, renamed
    except OutputError as error:
        raise SystemExit(f"error: {error}") from None


if __name__ == "__main__":
    main()
