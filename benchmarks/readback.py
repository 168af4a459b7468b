"""Suite ``readback``: what reading a trace costs against the run that wrote it, in one sitting.

A researcher's loop is run, then report / stability / map. Every figure here is a whole process as the
user starts it (interpreter start-up, imports, the work, exit), timed against the process that wrote
the trace, in the same rounds (variants interleaved, rotated each round; medians):

* ``study``: the string-stability study's cacc run (configs/study/string_stability.toml, 7 vehicles with
  links, 10 283 steps) by ``platoon run -q``, against ``load`` of its trace in a fresh interpreter, a 10 s
  slice of it (``load(start=100, end=110)``, against the whole ``load`` in the same interpreter), and
  ``platoon stability`` of it;
* ``readme``: the README's ``platoon run configs/paper/platoon.toml``, against ``platoon report`` of its
  trace and ``platoon report --plots``;
* ``map`` (``--map``; about a minute): the study's 75-run sweep (configs/sweeps/string_stability.toml) by
  ``platoon sweep``, against ``platoon stability-map`` of it;
* ``memory``: a ``load`` of the study trace in a fresh interpreter, its peak allocations (tracemalloc, numpy's
  included) against the bytes of the arrays it returns.
"""

from __future__ import annotations

import json
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

from .common import BenchError, BenchUsageError, Progress, interleaved, markdown_table

STUDY = Path("configs") / "study" / "string_stability.toml"
STUDY_SETS = ["--set", "platoon.speed_law=cacc", "--set", "links.delay=0.3"]
README = Path("configs") / "paper" / "platoon.toml"
SWEEP = Path("configs") / "sweeps" / "string_stability.toml"

# What a child interpreter does to time load in-process: the whole trace, then a 10 s slice of it
_LOAD = """
import json, sys, time
from orchestrator.trace import load
started = time.perf_counter(); trace = load(sys.argv[1]); whole = time.perf_counter() - started
started = time.perf_counter(); load(sys.argv[1], start=100.0, end=110.0); part = time.perf_counter() - started
print(json.dumps({"whole": whole, "slice": part}))
"""

_MEMORY = """
import json, sys, tracemalloc
from orchestrator.trace import load
tracemalloc.start(); trace = load(sys.argv[1]); peak = tracemalloc.get_traced_memory()[1]; tracemalloc.stop()
arrays = sum(a.nbytes for group in (*trace.channels.values(), *trace.live.values(), trace.errors) for a in group.values())
print(json.dumps({"peak": peak, "arrays": arrays}))
"""


def _platoon(*args: str) -> list[str]:
    return [sys.executable, "-c", "from orchestrator.cli import main; main()", *args]


def _timed(command: list[str], what: str) -> tuple[float, str]:
    started = time.perf_counter()
    done = subprocess.run(command, capture_output=True, text=True, timeout=3600)
    wall = time.perf_counter() - started
    if done.returncode != 0:
        raise BenchError(f"{what}: exit {done.returncode}: {done.stderr[-2000:]}")
    return wall, done.stdout


class _Sitting:
    """The traces each round writes, and the commands that read them."""

    def __init__(self, scratch: Path) -> None:
        self.scratch = scratch
        self.study = scratch / "study.mcap"
        self.readme = scratch / "platoon.mcap"
        self.sweep = scratch / "sweep"
        self.plots = scratch / "plots"

    def measure(self, group: str, variant: str) -> dict[str, Any]:
        sample: dict[str, Any] = {"group": group, "variant": variant}
        if variant == "run":
            out = {"study": self.study, "readme": self.readme}[group]
            # the study's run as a sweep runs it (-q), the README's as the README writes it (progress, table)
            config, sets = (STUDY, [*STUDY_SETS, "-q"]) if group == "study" else (README, [])
            sample["wall"], _ = _timed(_platoon("run", str(config), *sets, "--out", str(out)), f"{group} run")
        elif variant == "load":
            sample["wall"], stdout = _timed([sys.executable, "-c", _LOAD, str(self.study)], "load")
            sample.update(json.loads(stdout.strip().splitlines()[-1]))
        elif variant == "stability":
            sample["wall"], _ = _timed(_platoon("stability", str(self.study)), "platoon stability")
        elif variant == "report":
            sample["wall"], _ = _timed(_platoon("report", str(self.readme)), "platoon report")
        elif variant == "report --plots":
            sample["wall"], _ = _timed(_platoon("report", str(self.readme), "--plots", str(self.plots)), "report --plots")
        elif variant == "sweep":
            shutil.rmtree(self.sweep, ignore_errors=True)
            sample["wall"], _ = _timed(_platoon("sweep", str(SWEEP), "--out", str(self.sweep), "-q"), "platoon sweep")
        elif variant == "stability-map":
            png = self.scratch / "stability.png"
            sample["wall"], _ = _timed(_platoon("stability-map", str(self.sweep), "--out", str(png)), "stability-map")
        else:  # memory
            sample["wall"], stdout = _timed([sys.executable, "-c", _MEMORY, str(self.study)], "memory")
            sample.update(json.loads(stdout.strip().splitlines()[-1]))
        return sample


VARIANTS = {
    "study": ["run", "load", "stability", "memory"],
    "readme": ["run", "report", "report --plots"],
    "map": ["sweep", "stability-map"],
}


def run(rounds: int, with_map: bool, progress: Progress | None = None) -> dict[str, Any]:
    for path in (STUDY, README) + ((SWEEP,) if with_map else ()):
        if not path.is_file():
            raise BenchUsageError(f"{path}: not found (run the benchmark from the repository)")
    groups = ["study", "readme"] + (["map"] if with_map else [])
    with tempfile.TemporaryDirectory(prefix="bench-readback-") as scratch_name:
        sitting = _Sitting(Path(scratch_name))
        # each group's writer runs first in every round (its readers need its file), the readers rotate after it
        samples = interleaved(rounds, groups, [], lambda group, variant: sitting.measure(group, variant),
                              lambda s: f"{s['group']} {s['variant']}: {s['wall']:.2f} s", progress,
                              variants_of=lambda group: VARIANTS[group])
    return {"rounds": rounds, "samples": samples, "medians": _medians(samples)}


def _medians(samples: list[dict[str, Any]]) -> dict[str, dict[str, float]]:
    medians: dict[str, dict[str, float]] = {}
    for sample in samples:
        medians.setdefault(f"{sample['group']} {sample['variant']}", {})
    for key in medians:
        mine = [s for s in samples if f"{s['group']} {s['variant']}" == key]
        for field in ("wall", "whole", "slice", "peak", "arrays"):
            if field in mine[0]:
                medians[key][field] = statistics.median(s[field] for s in mine)
    return medians


def render(result: dict[str, Any]) -> str:
    m = result["medians"]
    rows = []
    writer = {"study": m["study run"]["wall"], "readme": m["readme run"]["wall"]}
    if "map sweep" in m:
        writer["map"] = m["map sweep"]["wall"]
    for key, values in m.items():
        group, variant = key.split(" ", 1)
        if variant in ("run", "sweep", "memory"):
            continue
        rows.append((key, f"{values['wall']:.2f}", f"{writer[group]:.2f}", f"{values['wall'] / writer[group]:.2f}"))
    lines = [f"reading traces against the runs that wrote them (whole processes, medians of {result['rounds']} rounds)",
             markdown_table(("reader", "s", "writer s", "reader / writer"), rows)]
    load = m["study load"]
    lines.append(f"in one interpreter: load of the study trace {load['whole']:.3f} s, a 10 s slice of it "
                 f"{load['slice']:.4f} s ({load['slice'] / load['whole']:.3f}x the whole load)")
    memory = m["study memory"]
    lines.append(f"load's peak allocations {memory['peak'] / 2**20:.1f} MiB for {memory['arrays'] / 2**20:.1f} MiB of "
                 f"arrays ({memory['peak'] / memory['arrays']:.2f}x)")
    return "\n".join(lines)
