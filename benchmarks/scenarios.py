"""Suite ``scenarios``: whole-run wall times of the paper's scenarios, start-up included (a
user waits for the whole process, not only its steps).

Every run is a whole process, timed from outside from its start to its exit (``os.wait4``, which also
gives its CPU time and peak RSS), for each engine (native, python) and variant:

* ``cli-traced``: ``platoon run CONFIG --out TRACE -q``, exactly what a user runs;
* ``traced``: a fresh interpreter that loads the config and calls ``run_scenario(config, text, TRACE)``;
* ``untraced``: the same with ``out=None`` (nothing recorded). ``platoon run`` has no option to run
  without a trace, hence this entry point (``benchmarks.child``, task ``wholerun``).

``traced`` against ``cli-traced`` shows what the CLI's own imports add; ``traced`` against
``untraced`` what the trace costs the whole run. Start-up is the process's wall time minus the run's
own wall time (``run_scenario``'s, printed by ``platoon run``: from before the trace writer is opened
to after it is closed; what is left is the interpreter, imports, config, FMU build check and unzip).
"""

from __future__ import annotations

import json
import os
import re
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import TYPE_CHECKING, Any, Sequence

from fmus.builders import DEFAULT_OUT

from .common import PAPER_CONFIGS, RESULT, BenchError, BenchUsageError, Progress, interleaved, markdown_table

if TYPE_CHECKING:  # the child imports these only once it runs a scenario: its start-up is measured
    from orchestrator.scenario.config import Config
    from orchestrator.execution.run import RunResult

ENGINES = ("native", "python")
VARIANTS = ("cli-traced", "traced", "untraced")
_CLI_DONE = re.compile(r"\((\d+) steps in ([0-9.]+) s\)")


def run_config(config: Path, engine: str | None, out: Path | None, overrides: Sequence[str], fmu_dir: Path,
               trace_writer: str = "auto") -> tuple[Config, RunResult]:
    """Load ``config`` with ``overrides`` and run it as ``platoon run`` does (``out=None``: no trace).

    The one way every whole-run benchmark (this suite, ``paper_scenarios``, ``trace_overhead``) runs a
    scenario, so that they all measure what a user runs. ``engine=None``: the default engine.
    """
    from orchestrator.scenario.config import load_config
    from orchestrator.execution.run import run_scenario

    parsed, _ = load_config(config, list(overrides))
    return parsed, run_scenario(parsed, config.read_text(), out, engine=engine, fmu_dir=fmu_dir,
                                trace_writer=trace_writer)


def whole_run(config: Path, engine: str, out: str | None, overrides: list[str], fmu_dir: Path) -> dict[str, Any]:
    """Child side of ``traced``/``untraced``: what ``platoon run -q`` does, with or without the trace."""
    _, result = run_config(config, engine, Path(out) if out else None, overrides, fmu_dir)
    return {"status": result.status, "error": result.error, "steps": result.steps, "run_wall_s": result.wall_time}


def platoon_command() -> list[str]:
    """The installed ``platoon`` console script next to this interpreter (else the same entry point)."""
    script = Path(sys.executable).parent / "platoon"
    if script.is_file():
        return [str(script)]
    return [sys.executable, "-c", "from orchestrator.cli import main; main()"]


def timed_process(command: list[str], scratch: Path) -> tuple[float, dict[str, Any], str, str]:
    """Run ``command`` to its exit: (wall seconds, {exit, user_s, sys_s, max_rss_kib}, stdout, stderr)."""
    with open(scratch / "stdout", "w+") as stdout, open(scratch / "stderr", "w+") as stderr:
        started = time.perf_counter()
        process = subprocess.Popen(command, stdout=stdout, stderr=stderr, stdin=subprocess.DEVNULL,
                                   env=_timed_environment())
        _, status, usage = os.wait4(process.pid, 0)
        wall = time.perf_counter() - started
        process.returncode = os.waitstatus_to_exitcode(status)
        stdout.seek(0)
        stderr.seek(0)
        text, errors = stdout.read(), stderr.read()
    return wall, {"exit": process.returncode, "user_s": usage.ru_utime, "sys_s": usage.ru_stime,
                  "max_rss_kib": usage.ru_maxrss}, text, errors


def _timed_environment() -> dict[str, str]:
    """A timed process's environment: no colour, and its bytecode cache used as an installed tool uses it
    (``PYTHONDONTWRITEBYTECODE`` dropped: a warm-up run writes the cache, the timed ones read it)."""
    environment = {key: value for key, value in os.environ.items() if key != "PYTHONDONTWRITEBYTECODE"}
    return {**environment, "NO_COLOR": "1", "TERM": "dumb"}


def measure(config: Path, engine: str, variant: str, overrides: list[str], fmu_dir: Path, scratch: Path) -> dict[str, Any]:
    trace = scratch / "trace.mcap"
    trace.unlink(missing_ok=True)
    if variant == "cli-traced":
        sets = [arg for override in overrides for arg in ("--set", override)]
        command = [*platoon_command(), "run", str(config), "--out", str(trace), "-q", "--engine", engine, *sets]
    else:
        task = {"kind": "wholerun", "config": str(config), "engine": engine, "overrides": overrides,
                "out": str(trace) if variant == "traced" else None, "fmu_dir": str(fmu_dir)}
        command = [sys.executable, "-m", "benchmarks.child", json.dumps(task)]
    wall, usage, stdout, stderr = timed_process(command, scratch)
    if usage["exit"] != 0:
        raise BenchError(f"{' '.join(command)} exited {usage['exit']}:\n{stdout[-2000:]}\n{stderr[-2000:]}")
    if variant == "cli-traced":
        done = _CLI_DONE.search(stdout)
        if done is None:
            raise BenchError(f"no '(N steps in T s)' in the output of {' '.join(command)}:\n{stdout[-2000:]}")
        steps, run_wall = int(done.group(1)), float(done.group(2))
    else:
        line = next((line for line in stdout.splitlines() if line.startswith(RESULT)), None)
        if line is None:
            raise BenchError(f"no result from {' '.join(command)}:\n{stdout[-2000:]}\n{stderr[-2000:]}")
        child = json.loads(line[len(RESULT):])
        if child["status"] != "completed":
            raise BenchError(f"{config} with {engine} {child['status']}: {child['error']}")
        steps, run_wall = child["steps"], child["run_wall_s"]
    trace_bytes = trace.stat().st_size if trace.exists() else None
    if (variant == "untraced") != (trace_bytes is None):
        raise BenchError(f"{config} {engine} {variant}: trace file {'missing' if trace_bytes is None else 'written'}")
    return {"config": config.stem, "engine": engine, "variant": variant, "wall_s": wall, "run_wall_s": run_wall,
            "startup_s": wall - run_wall, "steps": steps, "trace_bytes": trace_bytes, **usage}


def find_configs(configs: Sequence[Path] | None) -> list[Path]:
    found = list(configs) if configs else sorted(PAPER_CONFIGS.glob("*.toml"))
    if not found:
        raise BenchUsageError(f"no scenario configs: none given and no {PAPER_CONFIGS}/*.toml in {Path.cwd()} "
                         "(run from the repository, or pass --config)")
    missing = [str(p) for p in found if not p.is_file()]
    if missing:
        raise BenchUsageError(f"config(s) not found: {', '.join(missing)}")
    return found


def run(configs: Sequence[Path] | None = None, engines: Sequence[str] = ENGINES, variants: Sequence[str] = VARIANTS,
        rounds: int = 3, overrides: Sequence[str] = (), fmu_dir: Path = DEFAULT_OUT,
        progress: Progress | None = None) -> dict[str, Any]:
    unknown = [e for e in engines if e not in ENGINES] + [v for v in variants if v not in VARIANTS]
    if unknown:
        raise BenchUsageError(f"unknown engine(s)/variant(s) {', '.join(unknown)}; engines: {', '.join(ENGINES)}, "
                         f"variants: {', '.join(VARIANTS)}")
    paths = find_configs(configs)
    from orchestrator.scenario.config import ConfigError, load_config
    from orchestrator.scenario.limits import check_run_size

    for path in paths:  # a bad config or override, or an absurdly long run, is a usage error before anything runs
        try:
            config = load_config(path, list(overrides))[0]
        except ConfigError as error:
            raise BenchUsageError(f"config {path}: {error}") from None
        try:
            check_run_size(config)
        except ConfigError as error:
            raise BenchUsageError(f"config {path}: {error}; benchmarks take no --allow-long: time a shorter run") from None
    from .platoon import fmu_files

    fmu_files(fmu_dir)  # build once, as the first `platoon run` would
    started = time.perf_counter()
    folder = Path(fmu_dir).resolve()

    def describe(result: dict[str, Any]) -> str:
        return (f"{result['config']:<24} {result['engine']:<7} {result['variant']:<10} {result['wall_s']:7.2f} s "
                f"(start-up {result['startup_s']:.2f} s)")

    with tempfile.TemporaryDirectory(prefix="bench-scenarios-") as scratch:
        samples = interleaved(rounds, [p.resolve() for p in paths], [(e, v) for e in engines for v in variants],
                              lambda path, combo: measure(path, *combo, list(overrides), folder, Path(scratch)),
                              describe, progress)
    medians: dict[str, dict[str, dict[str, dict[str, float]]]] = {}
    for path in paths:
        for engine in engines:
            for variant in variants:
                mine = [s for s in samples if s["config"] == path.stem and s["engine"] == engine and s["variant"] == variant]
                medians.setdefault(path.stem, {}).setdefault(engine, {})[variant] = {
                    key: statistics.median(s[key] for s in mine)
                    for key in ("wall_s", "run_wall_s", "startup_s", "user_s", "sys_s", "max_rss_kib")}
    ratios: dict[str, dict[str, float]] = {}
    for name, by_engine in medians.items():
        mine = ratios.setdefault(name, {})
        if {"native", "python"} <= set(by_engine):
            for variant in variants:
                mine[f"python / native ({variant})"] = by_engine["python"][variant]["wall_s"] / by_engine["native"][variant]["wall_s"]
        for engine, by_variant in by_engine.items():
            if {"traced", "untraced"} <= set(by_variant):
                mine[f"{engine}: traced / untraced"] = by_variant["traced"]["wall_s"] / by_variant["untraced"]["wall_s"]
            if {"cli-traced", "traced"} <= set(by_variant):
                mine[f"{engine}: cli-traced / traced"] = by_variant["cli-traced"]["wall_s"] / by_variant["traced"]["wall_s"]
    return {"configs": [str(p) for p in paths], "engines": list(engines), "variants": list(variants),
            "rounds": rounds, "overrides": list(overrides), "cli": platoon_command(),
            "steps": {s["config"]: s["steps"] for s in samples}, "medians": medians, "ratios": ratios,
            "samples": samples, "seconds": time.perf_counter() - started}


def markdown(result: dict[str, Any]) -> str:
    engines, variants = result["engines"], result["variants"]
    header = ["scenario", "steps", *(f"{e} {v}" for e in engines for v in variants)]
    rows = [[name, result["steps"][name], *(f"{by_engine[e][v]['wall_s']:.2f} ({by_engine[e][v]['startup_s']:.2f})"
                                            for e in engines for v in variants)]
            for name, by_engine in result["medians"].items()]
    ratio_names = list(dict.fromkeys(k for r in result["ratios"].values() for k in r))
    ratio_rows = [[name, *(f"{result['ratios'][name].get(k, float('nan')):.2f}" for k in ratio_names)]
                  for name in result["medians"]]
    return (f"whole-process wall time in s (start-up in brackets: wall time minus the run's own), median of "
            f"{result['rounds']} interleaved rounds\n\n" + markdown_table(header, rows)
            + "\n\nratios of the medians (same run)\n\n" + markdown_table(["scenario", *ratio_names], ratio_rows))
