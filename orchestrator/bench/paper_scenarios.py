"""Run every paper scenario (configs/paper/*.toml) with both laws: summaries, peaks and wall times.

    .venv/bin/python benchmarks/paper_scenarios.py [--json runs/bench/paper_scenarios.json]

The numbers in docs/reproduction.md come from this script. Wall time is the whole run_scenario call
(FMUs already built): instantiation, initialization, stepping and trace writing.
"""

from __future__ import annotations

import argparse
import json
import tempfile
from pathlib import Path

from orchestrator.config import load_config
from orchestrator.metrics import report_json, summarize
from orchestrator.run import run_scenario
from orchestrator.trace import load

REPO = Path(__file__).resolve().parents[1]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--json", type=Path, default=REPO / "runs" / "bench" / "paper_scenarios.json")
    args = parser.parse_args()
    results = []
    with tempfile.TemporaryDirectory() as scratch:
        for path in sorted((REPO / "configs" / "paper").glob("*.toml")):
            for law in ("sine", "regular"):
                config, _ = load_config(path, [f"platoon.law={law}"])
                out = Path(scratch) / f"{path.stem}-{law}.mcap"
                result = run_scenario(config, path.read_text(), out)
                summary = report_json(summarize(load(out), config))
                record = {"scenario": path.stem, "law": law, "wall_time_s": round(result.wall_time, 3),
                          "steps": result.steps, "trace_bytes": out.stat().st_size, **summary}
                results.append(record)
                print(f"{path.stem:24s} {law:8s} {result.wall_time:6.2f} s  " + "  ".join(
                    f"{v['name']}: off {v['path_offset']:+.3g} gap {v['gap']:.5g} V {v['speed']:.5g} max|e| {v['path_error_max']:.3g}"
                    for v in summary["vehicles"]), flush=True)
    args.json.parent.mkdir(parents=True, exist_ok=True)
    args.json.write_text(json.dumps(results, indent=2))
    print(f"wrote {args.json}")


if __name__ == "__main__":
    main()
