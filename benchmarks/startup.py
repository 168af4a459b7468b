"""Suite ``startup``: what a user waits for before a command answers, and what a sweep pays per run beside
the run's own work, in one sitting.

* ``commands``: ``platoon --help``, ``--version``, a bad option, a 10-step ``platoon run -q`` of
  configs/paper/platoon.toml, the README's ``platoon run configs/paper/platoon.toml`` and ``platoon report``
  of its trace. Each is a whole process as the user starts it: the time to its first byte of output
  (either stream; a quiet run's first output is its exit) and to its exit. Each command runs once before
  the rounds (not counted): the bytecode cache is then written, and help pages are shown from their
  cache, as from a user's second time on (orchestrator/cli/help_cache.py).
* ``sweep``: a sweep of ``--runs`` runs of the paper platoon, ``--stop-time`` simulated seconds each (k_v
  varied), on one local worker: its wall time per run, against the run's own work, taken as
  ``platoon run -q`` of one of its runs minus a 10-step ``platoon run -q`` (what every process pays to
  start is left out of the work, so the ratio is the sweep's whole cost per run over the work alone).

Variants interleaved, rotated each round; medians. The load average is recorded at the start and the end:
on a loaded machine every figure grows; the ratios, taken in the same sitting, hold better.
"""

from __future__ import annotations

import os
import selectors
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

from .common import PAPER_CONFIGS, BenchError, BenchUsageError, Progress, interleaved, markdown_table
from .scenarios import _timed_environment  # the bytecode cache used, as an installed tool uses it

BASE = PAPER_CONFIGS / "platoon.toml"
TEN_STEPS = ["--set", "simulation.stop_time=0.1"]  # the paper config's step is 0.01 s
COMMANDS = ("--help", "--version", "bad option", "run 10 steps", "README run", "report")
LONG_RUN = "run of a sweep's length"  # one run as the sweep runs it, by `platoon run -q`


def _platoon(*args: str) -> list[str]:
    return [sys.executable, "-c", "from orchestrator.cli import main; main()", *args]


def _timed(command: list[str], what: str, codes: tuple[int, ...] = (0,)) -> tuple[float, float]:
    """(time to the first byte of output, time to exit) of ``command``, whole process."""
    started = time.perf_counter()
    process = subprocess.Popen(command, stdout=subprocess.PIPE, stderr=subprocess.PIPE, stdin=subprocess.DEVNULL,
                               env=_timed_environment())
    first, tail = None, b""
    with selectors.DefaultSelector() as selector:
        for stream in (process.stdout, process.stderr):
            selector.register(stream, selectors.EVENT_READ)
        while selector.get_map():
            for key, _ in selector.select():
                data = os.read(key.fd, 65536)
                if not data:
                    selector.unregister(key.fileobj)
                    continue
                first = first if first is not None else time.perf_counter() - started
                tail = (tail + data)[-2000:]
    code = process.wait()
    whole = time.perf_counter() - started
    if code not in codes:
        raise BenchError(f"{what}: exit {code}: {tail.decode(errors='replace')}")
    return (first if first is not None else whole), whole


class _Sitting:
    def __init__(self, scratch: Path, runs: int, stop_time: float) -> None:
        self.scratch = scratch
        self.trace = scratch / "platoon.mcap"
        self.stop_time = stop_time
        k_v = ", ".join(f"{0.5 + 0.01 * index:.2f}" for index in range(runs))
        self.sweep_file = scratch / "sweep.toml"
        self.sweep_file.write_text(f'base = "{BASE.resolve()}"\n[set]\n"simulation.stop_time" = {stop_time!r}\n'
                                   f'[grid]\n"platoon.k_v" = [{k_v}]\n')
        self.runs = runs

    def command(self, variant: str) -> tuple[list[str], tuple[int, ...]]:
        if variant == "bad option":
            return _platoon("--no-such-option"), (2,)
        if variant == "run 10 steps":
            return _platoon("run", str(BASE), *TEN_STEPS, "-q", "--out", str(self.scratch / "ten.mcap"), "--overwrite"), (0,)
        if variant == "README run":
            return _platoon("run", str(BASE), "--out", str(self.trace), "--overwrite"), (0,)
        if variant == "report":
            return _platoon("report", str(self.trace)), (0,)
        if variant == LONG_RUN:
            return _platoon("run", str(BASE), "--set", f"simulation.stop_time={self.stop_time!r}", "-q",
                            "--out", str(self.scratch / "one.mcap"), "--overwrite"), (0,)
        return _platoon(variant), (0,)  # --help, --version

    def measure(self, _group: Any, variant: str) -> dict[str, Any]:
        if variant == "sweep":
            out = self.scratch / "sweep"
            shutil.rmtree(out, ignore_errors=True)
            _, whole = _timed(_platoon("sweep", str(self.sweep_file), "--out", str(out), "--workers", "1", "-q"), "sweep")
            return {"variant": variant, "first": whole, "whole": whole, "per_run": whole / self.runs}
        command, codes = self.command(variant)
        first, whole = _timed(command, variant, codes)
        return {"variant": variant, "first": first, "whole": whole}


def run(runs: int, stop_time: float, rounds: int, sweep: bool, progress: Progress | None = None) -> dict[str, Any]:
    if not BASE.is_file():
        raise BenchUsageError(f"{BASE}: not found (run the benchmark from the repository)")
    variants = [*COMMANDS, *((LONG_RUN, "sweep") if sweep else ())]
    load_before = os.getloadavg()
    with tempfile.TemporaryDirectory(prefix="bench-startup-") as scratch:
        sitting = _Sitting(Path(scratch), runs, stop_time)
        for variant in COMMANDS:  # once, not counted: the README's trace for report, the help pages' cache
            sitting.measure(None, variant)
        samples = interleaved(rounds, [None], variants, sitting.measure,
                              lambda s: f"{s['variant']}: first output {s['first']:.3f} s, exit {s['whole']:.3f} s", progress)
    medians = {variant: {key: statistics.median(s[key] for s in samples if s["variant"] == variant)
                         for key in ("first", "whole", *(("per_run",) if variant == "sweep" else ()))}
               for variant in variants}
    result: dict[str, Any] = {"runs": runs, "stop_time": stop_time, "rounds": rounds, "samples": samples,
                              "medians": medians, "load_average": [load_before[0], os.getloadavg()[0]]}
    if sweep:
        work = medians[LONG_RUN]["whole"] - medians["run 10 steps"]["whole"]
        result["sweep"] = {"per_run": medians["sweep"]["per_run"], "work": work, "ratio": medians["sweep"]["per_run"] / work}
    return result


def render(result: dict[str, Any]) -> str:
    m = result["medians"]
    rows = [(f"`platoon {variant}`" if variant.startswith("--") else variant, f"{m[variant]['first']:.3f}",
             f"{m[variant]['whole']:.3f}") for variant in COMMANDS]
    readme = m["README run"]["whole"]
    lines = [f"time to first output and to exit (whole processes, medians of {result['rounds']} rounds; load average "
             f"{result['load_average'][0]:.1f} at the start, {result['load_average'][1]:.1f} at the end)",
             markdown_table(("command", "first output s", "exit s"), rows),
             f"report / the README's run: {m['report']['whole'] / readme:.2f}"]
    if "sweep" in result:
        sweep, whole_run = result["sweep"], m[LONG_RUN]["whole"]
        lines.append(f"sweep of {result['runs']} runs of {result['stop_time']:g} s, 1 worker: {sweep['per_run']:.3f} s a run; "
                     f"the run's own work {sweep['work']:.3f} s (run -q {whole_run:.3f} s - 10 steps "
                     f"{m['run 10 steps']['whole']:.3f} s): {sweep['ratio']:.2f}x")
    return "\n".join(lines)
