"""``platoon stability-map``: a string-stability sweep as maps, the analytic boundary over the measured points.

One panel per speed law, the age of information the receiver works with across (each link delay's
ages, from the step or the delay on its grid to one beacon period more), the loss rate up. Each run of
the sweep (configs/sweeps/string_stability.toml) is measured from its trace: the largest growth per link at
the probe frequencies (the config's sinusoids) over the links that measure propagation
(``error_gains.clean_order``, ``error_gains.run_headline``: weak probes left out), the number `platoon stability`'s headline
gives. That one number is each
dot's fill (on the colour scale) and its label; a lossy dot is one run of one seed. Under the dots, the
sampled-data cascade (orchestrator/analysis/sampled_chain.py) of each (delay, loss) on a finer grid: its
peak growth per link in colour (never below 1: every chain passes w -> 0 unchanged), the line where it
leaves 1 (the analytic boundary of string stability) solid, and the line where its largest growth at the
probe frequencies is 1 dashed (what the probes can see).
"""

from __future__ import annotations

import math
import multiprocessing
import textwrap
import os
from concurrent.futures import Future, ProcessPoolExecutor, as_completed
from contextlib import nullcontext
from pathlib import Path
from typing import Any, Callable

import matplotlib

matplotlib.use("Agg")  # files only; never needs a display
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
from matplotlib.colors import ListedColormap, Normalize  # noqa: E402

from orchestrator.analysis.error_gains import (clean_order, frequency_gains, predicted_gains, probe_frequencies,  # noqa: E402
                                               run_headline, steady_window, vehicle_errors)
from orchestrator.analysis.headline import Headline  # noqa: E402
from orchestrator.analysis.sizing import AnalysisRefused, check_analysis, nothing_arrives  # noqa: E402
from orchestrator.analysis.chain_model import ChainModel, chain_model  # noqa: E402
from orchestrator.analysis.sampled_chain import GROWTH_TOLERANCE, PeakGrowth, growth_per_link, peak_growth  # noqa: E402
from orchestrator.analysis.string_stability import interior_vehicle  # noqa: E402
from orchestrator.analysis.validity import departures_cell, departures_of_trace, split_at  # noqa: E402
from orchestrator.analysis.verdict import NOT_COMPUTED, ClosedFormVerdict, closed_form_verdict  # noqa: E402
from orchestrator.scenario.config import Config, config_from_mapping  # noqa: E402
from orchestrator.scenario.wiring import TARGET  # noqa: E402
from orchestrator.support.output import IMAGE, check_target, replacing  # noqa: E402
from orchestrator.sweep.plot import PlotError  # noqa: E402
from orchestrator.sweep.results import lookup, read_records  # noqa: E402  (the sweep folder's reading)

LAW, DELAY, LOSS = "platoon.speed_law", "links.delay", "links.loss"


def measured_gains(config: Config, trace_path: Path, chain: ChainModel) -> tuple[np.ndarray, np.ndarray | None, Headline]:
    """Per probe frequency, per link that measures propagation: the run's gains, and the sampled-data
    cascade's prediction for the same links of the same run (None where it does not apply); the run's
    headline (``error_gains.run_headline``: its growth, scatter and weak probes). ``chain``: the config's
    ``chain_model``."""
    from orchestrator.trace import load

    frequencies = probe_frequencies(config)
    if not frequencies:
        raise PlotError(f"{trace_path}: its config has no sinusoid to measure gains at")
    # what the gains need: the vehicles and the target (gaps from positions), not the links or the errors,
    # over the window they are fitted in (with an offset: no baseline from before the disturbance is needed),
    # that of a run to its stop time; read again from the start if the run ended early
    components = _bodies(config)
    expected = steady_window(config, config.simulation.stop_time)
    trace = load(trace_path, components=components, errors=False, start=expected[0])
    names = trace.vehicles()
    order = clean_order(config, names)
    if len(order) < 2:
        raise PlotError(f"{trace_path}: too few vehicles past the pushed ones to measure a link")
    window = steady_window(config, float(trace.component(order[0])["t"][-1]))
    if window[0] < expected[0] - 1e-9:
        trace = load(trace_path, components=components, errors=False)
    errors = vehicle_errors(trace, config)
    measured = np.array(frequency_gains(errors, order, frequencies, window))
    predicted = predicted_gains(config, names, order, frequencies, chain)
    return (measured, None if predicted is None else np.array(predicted),
            run_headline(config, errors, order, window, chain))


def _analytic(config: Config, delay: float, loss: float) -> tuple[PeakGrowth, float]:
    """(the peak growth per link and its frequency, the largest growth at the probe frequencies) of the
    sampled-data cascade of ``config`` with every link's delay and loss set."""
    changed = _with_link(config, delay, loss)
    chain, vehicle = chain_model(changed), interior_vehicle(changed)
    probes = growth_per_link(chain, vehicle, np.array(probe_frequencies(config))).max()
    return peak_growth(chain, vehicle), float(probes)


def _points(folder: Path) -> list[dict[str, Any]]:
    """The sweep's runs (not the invalid ones): where they sit, their config (and its mapping, for a worker
    process), the trace to measure (None for a failed run)."""
    points = []
    for record in read_records(folder):
        if record["status"] == "invalid":
            continue
        where = {key: lookup(record, key) for key in (LAW, DELAY, LOSS)}
        if any(value is None for value in where.values()):
            raise PlotError(f"run {record['id']}: no {', '.join(k for k, v in where.items() if v is None)} (not a "
                            "string-stability sweep: configs/sweeps/string_stability.toml)")
        config = config_from_mapping(record["config"])
        chain = chain_model(config)
        if chain.missing is not None:
            raise PlotError(f"run {record['id']}: the sampled-data cascade does not model {chain.missing}")
        try:  # sized before any work (analysis/sizing.py); links that deliver nothing make no chain to map
            check_analysis(config, chain=chain)
            cut = nothing_arrives(config)
        except AnalysisRefused as error:
            cut = str(error)
        if cut is not None:
            raise PlotError(f"run {record['id']}: {cut}")
        trace = folder / record["trace"] if record["status"] == "completed" else None
        if trace is not None and not trace.is_file():  # a FIFO (or a link to one) would block the reading forever
            raise PlotError(f"run {record['id']}: its trace {trace} is not a regular file (report and stability refuse "
                            "it too)")
        points.append({**where, "gain": math.nan, "headline": None, "deviation": math.nan, "config": config,
                       "raw": record["config"], "trace": trace, "left": "", "settling": ""})
    return points


def _point(raw: dict[str, Any], trace: Path | None,
           verdict: bool) -> tuple[Headline | None, float, ClosedFormVerdict | None, str, str]:
    """One run's (headline: its growth per link, scatter, weak probes; None without gains; worst deviation
    from the cascade's prediction; the closed form's verdict if ``verdict``, else None: the analytic grid has
    its peak; where it left the model from the first disturbance on, "" if it did not, and then no gains;
    where it left it while it settled, before), from its config's mapping (a task of a worker process)."""
    config = config_from_mapping(raw)
    chain = chain_model(config)
    stable = closed_form_verdict(config, mean_square=False, chain=chain) if verdict else None
    if trace is None:
        return None, math.nan, stable, "", ""
    from orchestrator.trace import load

    start = min(d.start for d in config.disturbance)
    found = departures_of_trace(load(trace, components=_bodies(config), errors=False), config)
    settling, departures = (departures_cell(part) for part in split_at(found, start))
    if departures:
        return None, math.nan, stable, departures, settling
    measured, predicted, headline = measured_gains(config, trace, chain)
    return headline, float(np.abs(measured / predicted - 1.0).max()), stable, "", settling


def _bodies(config: Config) -> list[str]:
    """The components the gains and the validity check read: the target and the vehicles."""
    return [TARGET] + [f"vehicle{k}" for k in range(1, config.platoon.count + 1)]


def grid_axis(values: list[float], most: int) -> np.ndarray:
    """The analytic grid along one axis, 0 to the largest run's value: the most points up to ``most``
    (evenly spaced) on which every run's value lies, so that each run's closed-form verdict is a grid
    cell's (the study's delays 0 ... 0.4 by 0.1: 9 points, 0.05 apart), else ``most`` points."""
    top = max(values)
    for count in range(most, 1, -1):
        axis = np.linspace(0.0, top, count)
        if all(np.abs(axis - value).min() <= 1e-9 for value in values):
            return axis
    return np.linspace(0.0, top, most)


def _chain_key(config: Config) -> tuple:
    """What the closed form's peak depends on: the interior vehicle as the cascade sees it, the step and
    the lifting period (runs and grid cells with the same key have the same verdict)."""
    chain = chain_model(config)
    return (chain.vehicle(interior_vehicle(config)), chain.step, chain.lifting_period())


def _with_link(config: Config, delay: float, loss: float) -> Config:
    return config.model_copy(update={"links": config.links.model_copy(update={"delay": delay, "loss": loss})})


def agreement_lines(points: list[dict[str, Any]], stable: dict[str, dict[tuple[float, float], ClosedFormVerdict]]) -> list[str]:
    """Per law: how far the measured gains are from the cascade's prediction for the same links (worst over
    links and probes, by loss rate), and in how many runs the headline verdict (measured growth per link above 1)
    is the closed form's."""
    lines = []
    for law, verdicts in stable.items():
        for p in (p for p in points if p[LAW] == law and (p["left"] or p["settling"])):
            lines.append(f"{law}: run at delay {p[DELAY]:g} s, loss {p[LOSS]:g} left the model " + (
                f"({p['left']}): no gain" if p["left"] else f"while it settled ({p['settling']}) and came back: gain shown"))
        # every run that stays inside the model has a headline; one whose probes are all weak has no gain but is
        # counted (with no probe to judge), never silently dropped
        mine = [p for p in points if p[LAW] == law and not p["left"] and p["headline"] is not None]
        gained = [p for p in mine if not math.isnan(p["gain"])]
        worst = {loss: max(p["deviation"] for p in gained if p[LOSS] == loss) for loss in sorted({p[LOSS] for p in gained})}
        judged = [p for p in mine if p["headline"].verdict in ("grows", "does not grow")]
        agree = sum((p["headline"].verdict == "grows") == (not verdicts[(p[DELAY], p[LOSS])].string_stable) for p in judged)
        noisy = [p for p in mine if p not in judged]
        lines += [f"{law}: run at delay {p[DELAY]:g} s, loss {p[LOSS]:g}: {p['headline'].text()}" for p in noisy]
        unknown = sorted({f"delay {k[0]:g} s, loss {k[1]:g}: {v.loop.reason}" for k, v in verdicts.items()
                          if v.loop.state == NOT_COMPUTED})
        lines += [f"{law}: the closed form's loop not computed at {where} (the cascade's verdict alone)" for where in unknown]
        by_loss = ", ".join(f"{100 * deviation:.2f} % at loss {loss:g}" for loss, deviation in worst.items())
        lines.append(f"{law}: measured vs the cascade, worst over links and probes: {by_loss}; headline verdict = "
                     f"closed form's in {agree} of the {len(judged)} runs outside the noise ({len(noisy)} inside it or "
                     "with no probe to judge)")
    return lines


def colour_scale(highest: float) -> tuple[Normalize, ListedColormap]:
    """A linear scale from 0.98 to ``highest``: 1 to ``highest`` in reds (where peaks are), the sliver below 1
    in blues (only measured gains of stable chains fall there)."""
    top = max(highest, 1.05)
    below = max(1, round(256 * 0.02 / (top - 0.98)))
    colours = np.vstack([plt.get_cmap("Blues_r")(np.linspace(0.35, 0.9, below)),
                         plt.get_cmap("Reds")(np.linspace(0.05, 1.0, 256 - below))])
    return Normalize(vmin=0.98, vmax=top), ListedColormap(colours)


def age_label(config: Config, delay: float) -> str:
    """The delay and the ages of information it gives the receiver: from a0 = max(step, delay on the step
    grid) (Jacobi: a Link is one more hop) to a0 + the beacon period."""
    step = config.simulation.step
    first = max(step, math.ceil(delay / step - 1e-9) * step)
    period = max(config.links.period, step)
    return f"{delay:g}\n{first:.2g}-{first + period:.2g}"


def _analytic_row(raw: dict[str, Any], delays: np.ndarray, loss: float) -> list[tuple[PeakGrowth, float]]:
    """``_analytic`` along the delays at one loss (a task of a worker process)."""
    config = config_from_mapping(raw)
    return [_analytic(config, float(delay), loss) for delay in delays]


def tasks(points: list[dict[str, Any]], laws: list[str], losses: np.ndarray) -> int:
    """How many tasks ``_compute`` counts: a run each, and a row of the analytic grid per law and loss."""
    return len(points) + len(laws) * len(losses)


def _compute(points: list[dict[str, Any]], laws: list[str], delays: np.ndarray, losses: np.ndarray,
             tick: Callable[[int], None] | None, workers: int) -> tuple[dict[str, tuple[np.ndarray, np.ndarray]],
                                                                          dict[str, dict[tuple[float, float], ClosedFormVerdict]]]:
    """Every run's measured gain and deviation (into the points), each law's analytic grid and the closed
    form's verdict per run, on ``workers`` processes: the grid's rows first, then the runs, each a task;
    ``tick(done)`` counts them as they finish."""
    first = {law: next(p for p in points if p[LAW] == law) for law in laws}  # each law's grid is its first run's
    done = 0
    pool = ProcessPoolExecutor(workers, mp_context=multiprocessing.get_context("fork")) if workers > 1 else None

    def submit(function: Callable[..., Any], *args: Any) -> Future:
        if pool is not None:
            return pool.submit(function, *args)
        future: Future = Future()
        future.set_result(function(*args))
        return future

    # each grid cell's key, for the runs whose verdict a cell already computes (the cell's peak)
    cells = {_chain_key(_with_link(first[law]["config"], float(delay), float(loss))): (law, i, j)
             for law in laws for i, loss in enumerate(losses) for j, delay in enumerate(delays)}
    from_grid = {id(p): cells.get(_chain_key(p["config"])) for p in points}
    with pool if pool is not None else nullcontext():
        rows = {law: [submit(_analytic_row, first[law]["raw"], delays, float(loss)) for loss in losses] for law in laws}
        runs = {submit(_point, p["raw"], p["trace"], from_grid[id(p)] is None): p for p in points}
        stable: dict[str, dict[tuple[float, float], ClosedFormVerdict]] = {law: {} for law in laws}
        for task in as_completed([*(t for law_rows in rows.values() for t in law_rows), *runs]):
            if task in runs:
                p = runs[task]
                p["headline"], p["deviation"], stable[p[LAW]][(p[DELAY], p[LOSS])], p["left"], p["settling"] = task.result()
                p["gain"] = p["headline"].growth if p["headline"] is not None else math.nan
            done += 1
            if tick is not None:
                tick(done)
        cells = {law: [task.result() for task in law_rows] for law, law_rows in rows.items()}  # loss x delay
    grids = {law: (np.array([[peak.gain for peak, _ in row] for row in found]),
                   np.array([[probes for _, probes in row] for row in found]),
                   np.array([[peak.frequency for peak, _ in row] for row in found])) for law, found in cells.items()}
    for p in points:
        if from_grid[id(p)] is not None:
            law, i, j = from_grid[id(p)]
            peak = cells[law][i][j][0]  # the cell's peak, as peak_growth gave it for the run's chain key
            stable[p[LAW]][(p[DELAY], p[LOSS])] = closed_form_verdict(p["config"], peak, mean_square=False)
    return grids, stable


def _panel(axis, mine: list[dict[str, Any]], grid: tuple[np.ndarray, ...], norm, cmap):
    delays, losses, peaks, probes, _ = grid
    image = axis.pcolormesh(delays, losses, np.clip(peaks, norm.vmin, norm.vmax), norm=norm, cmap=cmap, shading="nearest")
    if peaks.min() < 1.0 + GROWTH_TOLERANCE < peaks.max():  # the peak's verdict: string stable up to it
        axis.contour(delays, losses, peaks, levels=[1.0 + GROWTH_TOLERANCE], colors="black", linewidths=1.6)
    if probes.min() < 1.0 < probes.max():
        axis.contour(delays, losses, probes, levels=[1.0], colors="black", linewidths=1.0, linestyles="dashed")
    for p in mine:
        gain = p["gain"]
        if p["left"]:  # no gain: a cross, never a colour of the scale
            axis.scatter(p[DELAY], p[LOSS], s=70, marker="X", color="0.4", edgecolors="black", zorder=3)
        else:
            colour = "white" if math.isnan(gain) else cmap(norm(min(max(gain, norm.vmin), norm.vmax)))
            axis.scatter(p[DELAY], p[LOSS], s=70, color=colour, edgecolors="black", zorder=3)
        headline = p["headline"]
        label = ("left model" if p["left"] else "failed" if headline is None else "weak probes" if math.isnan(gain)
                 else f"{gain:.3f}")
        notes = [note for note, shown in (("noise", headline is not None and headline.verdict == "inside the noise"),
                                          ("left, settled", p["settling"] and not p["left"])) if shown]
        label += "".join(f"\n{note}" for note in notes)
        axis.annotate(label, (p[DELAY], p[LOSS]), textcoords="offset points", xytext=(0, 8), ha="center", fontsize=6,
                      bbox={"boxstyle": "round,pad=0.1", "facecolor": "white", "alpha": 0.8, "linewidth": 0})
    ticks = sorted({p[DELAY] for p in mine})
    axis.set_xticks(ticks, [age_label(mine[0]["config"], t) for t in ticks], fontsize=6)
    return image


def draw_stability_map(folder: Path, png: Path, overwrite: bool = False, resolution: int = 11,
                       progress: Callable[[int, int], Any] | None = None,
                       workers: int | None = None) -> tuple[Path, list[str]]:
    """Draw the map; return its path and ``agreement_lines`` (what the figure cannot show to 0.01 %).
    ``progress(runs, total)`` gives a context manager whose ``tick(done)`` counts the tasks done (a run
    measured, a row of an analytic grid: the CLI's bar or lines); ``workers`` processes share them
    (default: the usable CPUs)."""
    check_target(png, overwrite, [folder / "results.csv"], kind=IMAGE)  # before minutes of reading traces
    points = _points(folder)
    laws = list(dict.fromkeys(p[LAW] for p in points))
    delays = grid_axis([p[DELAY] for p in points], resolution)
    losses = grid_axis([p[LOSS] for p in points], resolution)
    if workers is None:
        workers = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)
    runs = sum(p["trace"] is not None for p in points)
    with (progress(runs, tasks(points, laws, losses)) if progress is not None else nullcontext()) as tick:
        grids, stable = _compute(points, laws, delays, losses, tick, workers)
    # the scale ends at the analysis's highest peak: a lossy run's single-seed gain beyond it shows in its
    # label, its dot at the scale's end
    norm, cmap = colour_scale(max(float(peaks.max()) for peaks, _, _ in grids.values()))
    figure, axes = plt.subplots(1, len(laws), figsize=(4.2 * len(laws) + 1.0, 4.6), dpi=120, squeeze=False,
                                sharey=True, layout="constrained")
    image = None
    for axis, law in zip(axes[0], laws):
        image = _panel(axis, [p for p in points if p[LAW] == law], (delays, losses, *grids[law]), norm, cmap)
        axis.set_title(f"speed_law = {law}")
        pad_x, pad_y = 0.06 * (delays[-1] or 1.0), 0.08 * (losses[-1] or 1.0)
        axis.set_xlim(-pad_x, delays[-1] + pad_x)
        axis.set_ylim(-pad_y, losses[-1] + pad_y)
        axis.set_xlabel("links.delay [s]\nage of information at the receiver [s]", fontsize=8)
    axes[0][0].set_ylabel("links.loss")
    title = ("String stability: the sampled-data cascade's peak growth per link (colour; solid line: 1, dashed: 1 at "
             "the probes) under each run's measured largest growth per link at the probes (dot and label; a lossy dot "
             "is one run of one seed; 'noise': inside 3 of its standard errors of 1; a cross: the run left the model, "
             "no gain; 'left, settled': it left it only while it settled)")
    figure.suptitle(textwrap.fill(title, int(figure.get_figwidth() * 15)), fontsize=8)  # ~15 characters an inch at 8 pt
    figure.colorbar(image, ax=axes[0].tolist(), label="gain per link", shrink=0.9, extend="max")
    try:  # the output rule (support/output.py): drawn aside, synced, renamed
        with replacing(png) as aside:
            figure.savefig(aside, format="png")
    finally:
        plt.close(figure)
    return png, agreement_lines(points, stable)
