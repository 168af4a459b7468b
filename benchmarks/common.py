"""What every benchmark suite shares: running one measurement in a fresh interpreter, interleaved
plans, medians, and the JSON result file with the versions and machine it was measured on."""

from __future__ import annotations

import json
import os
import platform
import subprocess
import sys
import time
from pathlib import Path
from typing import Any, Callable, Iterable, Sequence

RESULT = "RESULT "  # the one line of a child's stdout that carries its measurement (JSON)
DEFAULT_OUT_DIR = Path("runs") / "bench"
PAPER_CONFIGS = Path("configs") / "paper"  # like every path here, relative to the repository the benchmarks run from

# progress(done, total, line): called after every measurement with a one-line description of it
Progress = Callable[[int, int, str], None]


class BenchError(RuntimeError):
    """A measurement failed (its child process's output is in the message), or a suite cannot run."""


class BenchUsageError(BenchError):
    """Options a suite cannot run with (unknown engine, missing config, libcosimpy not installed)."""


def run_child(task: dict[str, Any], timeout: float = 3600.0) -> dict[str, Any]:
    """Run ``task`` in a fresh interpreter (``python -m benchmarks.child``) and return its result.

    A fresh process per measurement: no library, cache or heap state carries over, and the child
    leaves with ``os._exit`` so pythonfmu's interpreter teardown cannot crash or delay it.
    """
    process = subprocess.run([sys.executable, "-m", "benchmarks.child", json.dumps(task)],
                             capture_output=True, text=True, timeout=timeout)
    for line in process.stdout.splitlines():
        if line.startswith(RESULT):
            return json.loads(line[len(RESULT):])
    raise BenchError(f"{task.get('kind')} {task} failed (exit {process.returncode}):\n"
                     f"{process.stdout[-2000:]}\n{process.stderr[-4000:]}")


def rotated(items: Sequence[Any], round_: int) -> list[Any]:
    """``items`` rotated by the round number: no variant always runs first (or right after another)."""
    shift = round_ % len(items) if items else 0
    return list(items[shift:]) + list(items[:shift])


def interleaved(rounds: int, groups: Sequence[Any], variants: Sequence[Any],
                measure: Callable[[Any, Any], dict[str, Any]], describe: Callable[[dict[str, Any]], str],
                progress: Progress | None,
                variants_of: Callable[[Any], Sequence[Any]] | None = None) -> list[dict[str, Any]]:
    """``measure(group, variant)`` for every group and variant once per round, variants rotated each
    round; every result gets its ``round`` and is described to ``progress`` as it arrives (and the first one
    announced before it starts: a suite says it is measuring once its options have checked).
    ``variants_of(group)``: a group's own variants, when they are not ``variants`` for every group."""
    chosen = variants_of or (lambda group: variants)
    total = rounds * sum(len(chosen(group)) for group in groups)
    samples: list[dict[str, Any]] = []
    for round_ in range(rounds):
        for group in groups:
            for variant in rotated(chosen(group), round_):
                if progress is not None and not samples and round_ == 0:  # a first line before the first, slowest wait
                    progress(0, total, f"{total} measurements in {rounds} round(s), starting with {group} {variant}")
                result = measure(group, variant)
                result["round"] = round_
                samples.append(result)
                if progress is not None:
                    progress(len(samples), total, f"round {round_ + 1}/{rounds}  {describe(result)}")
    return samples


def slope(xs: Sequence[float], ys: Sequence[float]) -> tuple[float, float]:
    """Least-squares line y = a + b x through the points: (a, b)."""
    n = len(xs)
    mean_x, mean_y = sum(xs) / n, sum(ys) / n
    sxx = sum((x - mean_x) ** 2 for x in xs)
    if sxx == 0:
        return mean_y, 0.0
    b = sum((x - mean_x) * (y - mean_y) for x, y in zip(xs, ys)) / sxx
    return mean_y - b * mean_x, b


def rss_kib(pid: int | str = "self") -> int:
    """A process's resident set size (VmRSS of /proc/PID/status, Linux), KiB; this process by default.

    FileNotFoundError if the process is gone (a caller sampling other processes decides what that means).
    """
    with open(f"/proc/{pid}/status") as status:
        for line in status:
            if line.startswith("VmRSS:"):
                return int(line.split()[1])
    raise BenchError(f"no VmRSS in /proc/{pid}/status")


def versions() -> dict[str, str]:
    from importlib.metadata import PackageNotFoundError, version

    found = {"python": platform.python_version()}
    for package in ("platoon-cosim", "fmpy", "pythonfmu", "libcosimpy"):
        try:
            found[package] = version(package)
        except PackageNotFoundError:
            pass
    return found


def machine() -> dict[str, Any]:
    load = os.getloadavg() if hasattr(os, "getloadavg") else None
    return {"platform": platform.platform(), "cpus": os.cpu_count(), "processor": platform.processor(),
            "load_average_at_end": load}


def git_commit() -> str | None:
    try:
        done = subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True, timeout=10)
    except OSError:
        return None
    return done.stdout.strip() or None


def check_json_target(path: Path) -> None:
    """Refuse (``OutputError``, one line) a result file a benchmark must not replace, before it measures:
    by the output rule (orchestrator/support/output.py) only a missing or empty file or one holding JSON
    (a result of an earlier run) is replaced; never a FIFO, a device or a folder. Benchmarks have no
    ``--overwrite``: another file in the way is for the user to move."""
    from orchestrator.support.output import Kind, check_target, starts_with

    check_target(Path(path), kind=Kind("a JSON file", starts_with(b"{", b"[")), what="--json")


def write_json(path: Path, data: Any, indent: int = 1) -> Path:
    """``data`` as JSON to ``path`` by the output rule: checked (``check_json_target``), written aside,
    synced and renamed into place."""
    from orchestrator.support.output import write_text

    check_json_target(path)
    return write_text(Path(path), json.dumps(data, indent=indent), what="--json")


def write_result(out_dir: Path, suite: str, payload: dict[str, Any], out: Path | None = None) -> Path:
    """Write ``payload`` (plus versions, machine, commit, time) to ``out`` or ``out_dir/<suite>-<time>.json``."""
    path = out or out_dir / f"{suite}-{time.strftime('%Y%m%d-%H%M%S')}.json"
    record = {"suite": suite, **payload, "versions": versions(), "machine": machine(), "commit": git_commit(),
              "finished": time.strftime("%Y-%m-%dT%H:%M:%S%z")}
    return write_json(path, record)


def markdown_table(header: Sequence[str], rows: Iterable[Sequence[Any]]) -> str:
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    lines += ["| " + " | ".join(str(cell) for cell in row) + " |" for row in rows]
    return "\n".join(lines)
