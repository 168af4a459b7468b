"""Suite ``wholerun``: what a whole ``platoon run`` costs against libcosim running the same system (what a
user waits for, start-up and trace included, against the reference co-simulation tool).

Every sample is a whole process timed from outside (``timed_process``: start-up, stepping, tracing,
finalization, exit), on the paper platoon (configs/paper/platoon.toml, Jacobi) with N vehicles:

* ``platoon``: ``platoon run CONFIG --set platoon.count=N --out TRACE``, the default a user runs:
  progress bar off (not a terminal), every step traced, the summary table printed;
* ``platoon-q``: ``platoon run ... -q --trace-every 100``;
* ``platoon-start``: ``platoon run ... -q`` for 10 steps: start-up, what a short run (a sweep's) costs;
* ``platoon-first``: the same with ``-v``, which also says when the first step began (its
  ``first_step_s``: seconds from the process's start, docs/performance.md "Start-up");
* ``python``: ``python -c pass``, the interpreter's own start and exit: the floor of any start-up;
* ``libcosim-start``: libcosim (no observer) for the same 10 steps: its start-up;
* ``before``, ``before-q``, ``before-start``: the same three with another build's ``platoon`` script
  (``before=PATH``: e.g. a checkout of the previous commit installed in its own venv), so that a
  change is measured against what it replaces in the same sitting;
* ``libcosim``: libcosim (libcosimpy) from an SSP of the same system with ``numWorkerThreads=0``, no
  observer: nothing recorded;
* ``libcosim-outputs``: the same with a time-series observer on every output, every step: the values
  a traced run records (the baseline that does the work of ``platoon``);
* ``libcosim-last-value``: the same with libcosim's last-value observer, which reads every variable of
  every component after each step; the baseline the earlier per-step benchmark used (docs/performance.md
  says why that was not a fair reference);
* ``libcosim-file``: the same with libcosim's file observer (a CSV of every variable, every step): what
  libcosim does to keep a run on disk, the second baseline of a traced run;
* ``platoon-hour``: ``platoon run configs/bench/platoon100-1h.toml --out TRACE``, 100 vehicles for one
  simulated hour with its trace (the config's own size: measured once per round, whatever N).

Every process runs without ``PYTHONDONTWRITEBYTECODE``, so that it reads the bytecode cache that the
untimed first runs wrote, as an installed tool does (compiling the modules from source each time
would be measured otherwise). The SSP is written once, before timing (benchmarks/libcosim.py). Variants run interleaved and
rotated, ``rounds`` times; ratios are taken within a round (paired) and their median is reported.
"""

from __future__ import annotations

import json
import re
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any, Sequence

from fmus.builders import DEFAULT_OUT

from .common import PAPER_CONFIGS, RESULT, BenchError, BenchUsageError, Progress, interleaved, markdown_table
from .scenarios import platoon_command, timed_process

VARIANTS = ("platoon", "platoon-q", "platoon-start", "libcosim", "libcosim-outputs", "libcosim-last-value",
            "libcosim-file", "before", "before-q", "before-start", "platoon-first", "python", "libcosim-start",
            "platoon-hour")
DEFAULT_VARIANTS = ("platoon", "platoon-q", "platoon-start", "libcosim", "libcosim-file", "platoon-hour")
HOUR = "platoon-hour"  # its own config, measured once per round
HOUR_CONFIG = Path("configs") / "bench" / "platoon100-1h.toml"
HOUR_LIMIT = 5.0  # s of wall time the 100-vehicle hour with its trace may take (docs/performance.md's target: a long study stays at hand)
START_VARIANTS = ("platoon-start", "platoon-first", "python", "libcosim-start")  # 10-step runs: the start-up
START_STEPS = 10  # the start-up variants' run
OBSERVER = {"libcosim": "none", "libcosim-outputs": "outputs", "libcosim-last-value": "last-value",
            "libcosim-file": "file", "libcosim-start": "none"}
FIRST_STEP = re.compile(r"the first step began (\d+\.\d+) s after the process started")  # platoon run -v
START_TARGET = 0.2  # s: a run reaches its first step this soon (docs/performance.md, "Start-up": a sweep is made of short runs)
CONFIG = PAPER_CONFIGS / "platoon.toml"
SPARSE_TRACE = 100  # platoon-q records every 100th communication point
# the ratios docs/performance.md's targets bound: (name, numerator, denominator, upper bound)
FLOORS = (
    ("platoon / libcosim", "platoon", "libcosim", 1.5),
    ("platoon / libcosim-file", "platoon", "libcosim-file", 0.3),
    ("platoon-q / libcosim", "platoon-q", "libcosim", 1.15),
)
OTHER_RATIOS = (
    ("before / libcosim", "before", "libcosim"),
    ("before-q / libcosim", "before-q", "libcosim"),
    ("platoon / before", "platoon", "before"),
    ("platoon-q / before-q", "platoon-q", "before-q"),
    ("platoon-start / before-start", "platoon-start", "before-start"),
    ("platoon-start / python", "platoon-start", "python"),
    ("platoon-start / libcosim-start", "platoon-start", "libcosim-start"),
    ("libcosim-start / python", "libcosim-start", "python"),
    ("platoon / libcosim-outputs", "platoon", "libcosim-outputs"),
    ("libcosim-file / libcosim", "libcosim-file", "libcosim"),
    ("libcosim-outputs / libcosim", "libcosim-outputs", "libcosim"),
    ("libcosim-last-value / libcosim", "libcosim-last-value", "libcosim"),
)


def _overrides(n: int, steps: int, step: float) -> list[str]:
    return [f"platoon.count={n}", f"simulation.stop_time={steps * step!r}"]


def write_system(n: int, steps: int, step: float, folder: Path, fmu_dir: Path, fmus: str = "python") -> Path:
    """The SSD of the config's system with ``n`` vehicles and ``steps`` steps (libcosim, 0 worker threads):
    the package of ``platoon export-ssp``, unpacked into ``folder`` (libcosim then loads the .ssd as it
    did before the exporter existed, with no unzipping in the timed process)."""
    import zipfile

    from orchestrator.scenario.config import load_config
    from orchestrator.components.kinds import fmu_folder
    from orchestrator.scenario.scenario import build_scenario
    from orchestrator.interop.ssp import write_ssp

    from .platoon import fmu_files

    config, _ = load_config(CONFIG, _overrides(n, steps, step))
    if config.simulation.master != "jacobi":
        raise BenchError(f"{CONFIG}: master {config.simulation.master!r}; libcosim's fixed-step algorithm is Jacobi")
    package = write_ssp(folder / "platoon.ssp", build_scenario(config), fmu_files(fmu_folder(fmu_dir, fmus)),
                        worker_threads=0)
    with zipfile.ZipFile(package) as archive:
        archive.extractall(folder)
    return folder / "SystemStructure.ssd"


def measure(variant: str, n: int, steps: int, step: float, ssd: Path, scratch: Path, fmus: str = "python",
            before: Path | None = None, hour: Path = HOUR_CONFIG) -> dict[str, Any]:
    trace = scratch / "trace.mcap"
    trace.unlink(missing_ok=True)
    ours = variant.startswith(("platoon", "before"))
    kind = variant.split("-", 1)[1] if "-" in variant and ours and variant != HOUR else ""  # "", "q", "start" or "first"
    steps = START_STEPS if variant in START_VARIANTS or kind == "start" else steps
    if variant == HOUR:
        command = [*platoon_command(), "run", str(hour), "--out", str(trace), "--fmus", fmus]
    elif ours:
        if variant.startswith("before") and before is None:
            raise BenchUsageError(f"variant {variant} needs before=PATH (another build's platoon script)")
        sets = [arg for override in _overrides(n, steps, step) for arg in ("--set", override)]
        cli = [str(before)] if variant.startswith("before") else platoon_command()
        command = [*cli, "run", str(CONFIG), "--out", str(trace), "--fmus", fmus, *sets]
        if kind == "q":
            command += ["-q", "--trace-every", str(min(SPARSE_TRACE, steps))]  # at most the run's steps
        elif kind in ("start", "first"):
            command += ["-q", "-v"] if kind == "first" else ["-q"]
    elif variant == "python":
        command = [sys.executable, "-c", "pass"]
    else:
        command = [sys.executable, str(Path(__file__).with_name("libcosim_process.py")), str(ssd), str(steps),
                   OBSERVER[variant]]
    wall, usage, stdout, stderr = timed_process(command, scratch)
    if usage["exit"] != 0:
        raise BenchError(f"{' '.join(command)} exited {usage['exit']}:\n{stdout[-2000:]}\n{stderr[-2000:]}")
    sample = {"variant": variant, "n": n, "wall_s": wall, **usage}
    if ours:
        if not trace.is_file() or (kind == "") != ("max |path error|" in stdout):
            raise BenchError(f"{' '.join(command)}: no trace, or the summary table {'missing' if kind == '' else 'printed'}")
        if kind == "" and f"{fmus} FMUs" not in stdout:  # the summary's title names the FMUs stepped
            raise BenchError(f"{' '.join(command)}: the run did not step the {fmus} FMUs:\n{stdout[-2000:]}")
        if kind == "first":
            first = FIRST_STEP.search(stderr)
            if first is None:
                raise BenchError(f"{' '.join(command)}: no first-step time in its -v lines:\n{stderr[-2000:]}")
            sample["first_step_s"] = float(first.group(1))
    elif variant != "python":
        line = next((line for line in stdout.splitlines() if line.startswith(RESULT)), None)
        if line is None or json.loads(line[len(RESULT):])["time_ns"] != round(steps * step * 1e9):
            raise BenchError(f"{' '.join(command)}: libcosim did not reach the end:\n{stdout[-2000:]}")
    return sample


def run(ns: Sequence[int] = (16,), steps: int | Sequence[int] = 10_000, rounds: int = 5,
        variants: Sequence[str] = DEFAULT_VARIANTS,
        fmu_dir: Path = DEFAULT_OUT, progress: Progress | None = None, fmus: str = "python",
        before: Path | None = None, hour: Path = HOUR_CONFIG) -> dict[str, Any]:
    """Every variant steps the same FMUs, ``fmus`` ("python": the pythonfmu FMUs, the system whose cost
    against libcosim was asked for first; "native": the C twins), ours through ``platoon run --fmus`` and libcosim's
    from an SSP of the same files. ``steps``: one count for every N, or one per N (the paper platoon
    at N = 64 leaves its circle at t = 28 s, so it runs fewer steps than N = 16 in the same sitting).
    ``hour``: the config of ``platoon-hour`` (the 100-vehicle hour)."""
    counts = [steps] * len(ns) if isinstance(steps, int) else list(steps)
    if len(counts) != len(ns):
        raise BenchUsageError(f"{len(counts)} step counts for {len(ns)} vehicle counts: give one, or one per N")
    steps_of = dict(zip(ns, counts))
    if before is None and any(v.startswith("before") for v in variants):
        raise BenchUsageError("the before* variants need --before PLATOON (another build's platoon script)")
    unknown = [v for v in variants if v not in VARIANTS]
    if unknown:
        raise BenchUsageError(f"unknown variant(s) {', '.join(unknown)}; expected some of {', '.join(VARIANTS)}")
    for config in (CONFIG, hour) if HOUR in variants else (CONFIG,):
        if not config.is_file():
            raise BenchUsageError(f"{config} not found: run from the repository")
    try:
        import libcosimpy  # noqa: F401
    except ImportError:
        raise BenchUsageError("libcosimpy is not installed (pip install -e '.[test]')") from None
    from orchestrator.scenario.config import load_config

    step = load_config(CONFIG, [])[0].simulation.step
    started = time.perf_counter()
    with tempfile.TemporaryDirectory(prefix="bench-wholerun-") as scratch:
        systems = {n: write_system(n, steps_of[n], step, Path(scratch) / f"ssp-{n}", fmu_dir, fmus) for n in ns}
        # one untimed 10-step run of each variant first: FMUs built and extracted, bytecode cached, files in the
        # page cache
        warm = write_system(ns[0], 10, step, Path(scratch) / "warm", fmu_dir, fmus)
        for variant in dict.fromkeys(("platoon", "libcosim", *(v for v in variants if v != HOUR))):
            measure(variant, ns[0], 10, step, warm, Path(scratch), fmus, before)
        per_n = [v for v in variants if v != HOUR]
        groups = [*(ns if per_n else ()), *((HOUR,) if HOUR in variants else ())]
        samples = interleaved(rounds, groups, per_n,
                              lambda n, variant: measure(variant, n, steps_of.get(n, 1), step, systems.get(n),
                                                         Path(scratch), fmus, before, hour),
                              lambda s: f"N={s['n']:<4} {s['variant']:<20} {s['wall_s']:7.2f} s  {s['max_rss_kib'] / 1024:6.0f} MiB",
                              progress, variants_of=lambda group: [HOUR] if group == HOUR else per_n)
    medians = {n: {v: _median(samples, n, v) for v in per_n} for n in ns if per_n}
    hour_medians = _median(samples, HOUR, HOUR) if HOUR in variants else None
    ratios: dict[int, dict[str, float]] = {}
    for n in medians:
        by_round = {(s["round"], s["variant"]): s["wall_s"] for s in samples if s["n"] == n}
        for name, top, bottom, *_ in (*FLOORS, *OTHER_RATIOS):
            if top in variants and bottom in variants:
                ratios.setdefault(n, {})[name] = statistics.median(by_round[r, top] / by_round[r, bottom] for r in range(rounds))
        # the same floors in CPU time (user + system): what a loaded machine leaves readable
        cpu = {(s["round"], s["variant"]): s["user_s"] + s["sys_s"] for s in samples if s["n"] == n}
        for name, top, bottom, _ in FLOORS:
            if top in variants and bottom in variants:
                ratios[n][f"{name}, CPU"] = statistics.median(cpu[r, top] / cpu[r, bottom] for r in range(rounds))
    return {"config": str(CONFIG), "ns": list(ns), "steps": steps_of, "rounds": rounds, "variants": list(variants),
            "fmus": fmus, "before": None if before is None else str(before),
            "cli": platoon_command(), "medians": medians, "ratios": ratios,
            "floors": {name: floor for name, _, _, floor in FLOORS}, "samples": samples,
            "hour": None if hour_medians is None else {"config": str(hour), "limit_s": HOUR_LIMIT, **hour_medians},
            "seconds": time.perf_counter() - started}


def _median(samples: list[dict[str, Any]], group: Any, variant: str) -> dict[str, float]:
    """Median wall, user, system time and peak RSS of one variant's samples in one group (an N, or the
    hour), and when the first step began for ``platoon-first``."""
    return {key: statistics.median(s[key] for s in samples if s["n"] == group and s["variant"] == variant)
            for key in ("wall_s", "user_s", "sys_s", "max_rss_kib", "first_step_s")
            if key != "first_step_s" or variant == "platoon-first"}


def markdown(result: dict[str, Any]) -> str:
    variants = [v for v in result["variants"] if v != HOUR]
    hour = result.get("hour")
    tail = "" if hour is None else (
        f"\n\nplatoon-hour, with its trace ({hour['config']}): {hour['wall_s']:.2f} s wall, "
        f"{hour['user_s'] + hour['sys_s']:.2f} s CPU, {hour['max_rss_kib'] / 1024:.0f} MiB "
        f"(the 100-vehicle hour's target: ≤ {hour['limit_s']:g} s), median of {result['rounds']}")
    if not variants:
        return tail.strip()
    medians = result["medians"]
    rows = [[n, *(f"{medians[n][v]['wall_s']:.2f} ({medians[n][v]['user_s'] + medians[n][v]['sys_s']:.2f}; "
                  f"{medians[n][v]['max_rss_kib'] / 1024:.0f})" for v in variants)] for n in result["ns"]]
    names = list(dict.fromkeys(k for r in result["ratios"].values() for k in r))
    floors = result["floors"]
    ratio_rows = [[n, *(f"{result['ratios'][n][k]:.2f}" + (" (target ≤ %.2f)" % floors[k] if k in floors else "")
                        for k in names)] for n in result["ns"]]
    return (f"{result.get('fmus', 'python')} FMUs in every variant; "
            f"whole-process wall time in s (CPU s: user + system, the trace worker's included; peak RSS in MiB), "
            f"median of {result['rounds']} interleaved rounds, "
            f"{_steps_text(result['steps'])}\n\n" + markdown_table(["N", *variants], rows)
            + "\n\nratios, median of the per-round ratios\n\n" + markdown_table(["N", *names], ratio_rows)
            + start_up(result) + tail)


def start_up(result: dict[str, Any]) -> str:
    """The start-up figures (10-step runs), wall and CPU, and when the first step began, if measured."""
    shown = [v for v in START_VARIANTS if v in result["variants"]]
    if not shown:
        return ""
    lines = []
    for n in result["ns"]:
        medians = result["medians"][n]
        figures = [f"{v} {medians[v]['wall_s']:.3f} s wall ({medians[v]['user_s'] + medians[v]['sys_s']:.3f} s CPU)"
                   for v in shown]
        if "first_step_s" in medians.get("platoon-first", {}):
            figures.append(f"first step {medians['platoon-first']['first_step_s']:.2f} s after the process started "
                           f"(target <= {START_TARGET} s)")
        lines.append(f"N={n}: " + "; ".join(figures))
    return f"\n\nstart-up ({START_STEPS} steps), medians\n\n" + "\n".join(lines)


def _steps_text(steps: Any) -> str:
    """"10000 steps", or "10000 steps at N = 16, 2000 at N = 64" (``steps``: a count, or one per N)."""
    if not isinstance(steps, dict):
        return f"{steps} steps"
    if len(set(steps.values())) == 1:
        return f"{next(iter(steps.values()))} steps"
    return ", ".join(f"{count}{' steps' if i == 0 else ''} at N = {n}" for i, (n, count) in enumerate(steps.items()))
