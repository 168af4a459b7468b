"""``platoon stability-map``: a string-stability sweep as maps, the analytic boundary over the measured points.

One panel per speed law, link delay across, loss rate up. Each run of the sweep (configs/sweeps/
string_stability.toml) is measured from its trace: per probe frequency (the config's sinusoids), the
speed error's amplitude ratio over the chain's clean links (``error_gains.clean_order``), as one gain
per link (the geometric mean over those links); the point's gain is the largest over the probes. A
point is filled green when that gain is at most 1, red above. Under it, the analysis of each (delay,
loss) on a finer grid: its peak |G(jw)| in colour, the line where it is 1 (the analytic boundary of
string stability) solid, and the line where the largest |G| at the probe frequencies is 1 dashed (what
the probes can see: near the boundary a chain's peak sits at low frequencies, below the probes).
"""

from __future__ import annotations

import math
import multiprocessing
import os
from concurrent.futures import ProcessPoolExecutor, as_completed
from contextlib import nullcontext
from pathlib import Path
from typing import Any, Callable

import matplotlib

matplotlib.use("Agg")  # files only; never needs a display
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
from matplotlib.colors import TwoSlopeNorm  # noqa: E402

from orchestrator.analysis.error_gains import (clean_order, frequency_gains, probe_frequencies, steady_window,  # noqa: E402
                                               vehicle_errors)
from orchestrator.analysis.string_stability import chain_of, peak_gain  # noqa: E402
from orchestrator.scenario.config import Config, config_from_mapping  # noqa: E402
from orchestrator.scenario.wiring import TARGET  # noqa: E402
from orchestrator.support.output import IMAGE, check_target, replacing  # noqa: E402
from orchestrator.sweep.plot import PlotError  # noqa: E402
from orchestrator.sweep.results import lookup, read_records  # noqa: E402  (the sweep folder's reading)

LAW, DELAY, LOSS = "platoon.speed_law", "links.delay", "links.loss"


def measured_gain(config: Config, trace_path: Path) -> float:
    """The run's largest gain per link over its probe frequencies (geometric mean over the clean links)."""
    from orchestrator.trace import load

    # what the gains need: the vehicles and the target (gaps from positions), not the links or the errors, from
    # a second before the first disturbance (the state recorded before it is the errors' baseline) on
    first = min((d.start for d in config.disturbance), default=None)
    trace = load(trace_path, components=[TARGET] + [f"vehicle{k}" for k in range(1, config.platoon.count + 1)],
                 errors=False, start=None if first is None else max(0.0, first - 1.0))
    frequencies = probe_frequencies(config)
    order = clean_order(config, trace.vehicles())
    if not frequencies or len(order) < 2:
        raise PlotError(f"{trace_path}: its config has no sinusoid, or too few vehicles past the pushed ones")
    window = steady_window(config, float(trace.component(order[0])["t"][-1]))
    gains = frequency_gains(vehicle_errors(trace, config), order, frequencies, window)
    return max(math.prod(per_link) ** (1.0 / len(per_link)) for per_link in gains)


def _analytic(config: Config, delay: float, loss: float) -> tuple[float, float]:
    """(peak |G(jw)|, largest |G| at the probe frequencies) of ``config`` with every link's delay and loss set."""
    links = config.links.model_copy(update={"delay": delay, "loss": loss})
    chain = chain_of(config.model_copy(update={"links": links}))
    probes = np.abs(chain.transfer(np.array(probe_frequencies(config)))).max()
    return peak_gain(chain).gain, float(probes)


def _points(folder: Path) -> list[dict[str, Any]]:
    """The sweep's runs (not the invalid ones) with where they sit, their config, and the trace to measure."""
    points = []
    for record in read_records(folder):
        if record["status"] == "invalid":
            continue
        where = {key: lookup(record, key) for key in (LAW, DELAY, LOSS)}
        if any(value is None for value in where.values()):
            raise PlotError(f"run {record['id']}: no {', '.join(k for k, v in where.items() if v is None)} (not a "
                            "string-stability sweep: configs/sweeps/string_stability.toml)")
        trace = folder / record["trace"] if record["status"] == "completed" else None
        points.append({**where, "gain": math.nan, "config": config_from_mapping(record["config"]),
                       "raw": record["config"], "trace": trace})
    return points


def _measure(raw: dict[str, Any], trace: Path) -> float:
    """``measured_gain`` in a worker process (the config travels as its mapping)."""
    return measured_gain(config_from_mapping(raw), trace)


def _analytic_row(raw: dict[str, Any], delays: np.ndarray, loss: float) -> np.ndarray:
    """``_analytic`` along the delays at one loss: rows (peaks, probes)."""
    config = config_from_mapping(raw)
    return np.array([_analytic(config, float(delay), loss) for delay in delays]).T


def _grid(rows: list[np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    """(peaks, probes) of one law, rows by loss, from its ``_analytic_row``s."""
    stacked = np.array(rows)
    return stacked[:, 0, :], stacked[:, 1, :]


def _compute(points: list[dict[str, Any]], laws: list[str], delays: np.ndarray, losses: np.ndarray,
             tick: Callable[[int], None] | None, workers: int) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """Every point's measured gain (into the points) and each law's analytic grid, on ``workers`` processes:
    the grids' rows (the longest tasks) first, then the traces, each a task; ``tick(done)`` counts both
    as they finish (``tasks(points, laws, losses)`` of them)."""
    first = {law: next(p for p in points if p[LAW] == law)["raw"] for law in laws}
    measured = [p for p in points if p["trace"] is not None]
    done = 0

    def finished() -> None:
        nonlocal done
        done += 1
        if tick is not None:
            tick(done)

    rows: dict[str, list[Any]] = {law: [] for law in laws}
    if workers <= 1:
        for law in laws:
            for loss in losses:
                rows[law].append(_analytic_row(first[law], delays, float(loss)))
                finished()
        for p in measured:
            p["gain"] = measured_gain(p["config"], p["trace"])
            finished()
        return {law: _grid(rows[law]) for law in laws}
    with ProcessPoolExecutor(workers, mp_context=multiprocessing.get_context("fork")) as pool:
        grid_tasks = {law: [pool.submit(_analytic_row, first[law], delays, float(loss)) for loss in losses] for law in laws}
        tasks = {pool.submit(_measure, p["raw"], p["trace"]): p for p in measured}
        for task in as_completed([*tasks, *(t for law_tasks in grid_tasks.values() for t in law_tasks)]):
            if task in tasks:
                tasks[task]["gain"] = task.result()
            finished()
        return {law: _grid([task.result() for task in law_tasks]) for law, law_tasks in grid_tasks.items()}


def tasks(points: list[dict[str, Any]], laws: list[str], losses: np.ndarray) -> int:
    """How many tasks ``_compute`` counts: a trace each, and a row of the analytic grid per law and loss."""
    return sum(p["trace"] is not None for p in points) + len(laws) * len(losses)


def draw_stability_map(folder: Path, png: Path, overwrite: bool = False, resolution: int = 11,
                       progress: Callable[[int, int], Any] | None = None, workers: int | None = None) -> Path:
    """Measure every trace of the sweep in ``folder`` and draw the map into ``png``. ``progress(traces, total)``
    gives a context manager whose ``tick(done)`` counts the tasks done (a trace measured, a row of an
    analytic grid: the CLI's bar or lines); ``workers`` processes share them (default: the usable CPUs)."""
    check_target(png, overwrite, [folder / "results.csv"], kind=IMAGE)  # before minutes of reading traces
    points = _points(folder)
    laws = list(dict.fromkeys(p[LAW] for p in points))
    delays = np.linspace(0.0, max(p[DELAY] for p in points), resolution)
    losses = np.linspace(0.0, max(p[LOSS] for p in points), resolution)
    workers = workers if workers is not None else len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") \
        else (os.cpu_count() or 1)
    traces = sum(p["trace"] is not None for p in points)
    with (progress(traces, tasks(points, laws, losses)) if progress is not None else nullcontext()) as tick:
        grids = _compute(points, laws, delays, losses, tick, workers)
    figure, axes = plt.subplots(1, len(laws), figsize=(4.2 * len(laws) + 1.0, 4.2), dpi=120, squeeze=False,
                                sharey=True, layout="constrained")
    norm = TwoSlopeNorm(vcenter=1.0, vmin=0.8, vmax=1.6)
    image = None
    for axis, law in zip(axes[0], laws):
        mine = [p for p in points if p[LAW] == law]
        peaks, probes = grids[law]
        image = axis.pcolormesh(delays, losses, np.clip(peaks, norm.vmin, norm.vmax), norm=norm, cmap="RdBu_r",
                                shading="gouraud")
        if peaks.min() < 1.0 + 1e-12 < peaks.max():
            axis.contour(delays, losses, peaks, levels=[1.0 + 1e-9], colors="black", linewidths=1.6)
        if probes.min() < 1.0 < probes.max():
            axis.contour(delays, losses, probes, levels=[1.0], colors="black", linewidths=1.0, linestyles="dashed")
        for p in mine:
            unstable = not p["gain"] <= 1.0
            axis.scatter(p[DELAY], p[LOSS], s=70, c="#d62728" if unstable else "#2ca02c", edgecolors="black", zorder=3)
            label = "failed" if math.isnan(p["gain"]) else f"{p['gain']:.3f}"
            axis.annotate(label, (p[DELAY], p[LOSS]), textcoords="offset points", xytext=(0, 7), ha="center", fontsize=6)
        axis.set_title(f"speed_law = {law}")
        pad_x, pad_y = 0.06 * (delays[-1] or 1.0), 0.08 * (losses[-1] or 1.0)
        axis.set_xlim(-pad_x, delays[-1] + pad_x)
        axis.set_ylim(-pad_y, losses[-1] + pad_y)
        axis.set_xlabel("links.delay [s]")
    axes[0][0].set_ylabel("links.loss")
    figure.suptitle("String stability: analytic peak |G(jw)| (colour; solid line = 1, dashed = 1 at the probes)\n"
                    "over the measured gain per link (green <= 1, red > 1)", fontsize=9)
    figure.colorbar(image, ax=axes[0].tolist(), label="analytic peak |G(jw)|", shrink=0.9)
    try:  # the output rule (support/output.py): drawn aside, synced, renamed
        with replacing(png) as aside:
            figure.savefig(aside, format="png")
    finally:
        plt.close(figure)
    return png
