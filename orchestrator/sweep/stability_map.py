"""``platoon stability-map``: a string-stability sweep as maps, the analytic boundary over the measured points.

One panel per speed law, the age of information the receiver works with across (each link delay's
ages, from the step or the delay on its grid to one beacon period more), the loss rate up. Each run of
the sweep (configs/sweeps/string_stability.toml) is measured from its trace: the largest gain per link at
the probe frequencies (the config's sinusoids) over the links that measure propagation
(``error_gains.clean_order``), the number `platoon stability`'s headline gives. That one number is each
dot's fill (on the colour scale) and its label; a lossy dot is one run of one seed. Under the dots, the
sampled-data cascade (orchestrator/analysis/sampled_chain.py) of each (delay, loss) on a finer grid: its
peak growth per link in colour (never below 1: every chain passes w -> 0 unchanged), the line where it
leaves 1 (the analytic boundary of string stability) solid, and the line where its largest growth at the
probe frequencies is 1 dashed (what the probes can see).
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import matplotlib

matplotlib.use("Agg")  # files only; never needs a display
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
from matplotlib.colors import ListedColormap, Normalize  # noqa: E402

from orchestrator.analysis.error_gains import (clean_order, frequency_gains, predicted_gains, probe_frequencies,  # noqa: E402
                                               steady_window, vehicle_errors)
from orchestrator.analysis.sampled_chain import exact_applies, growth_per_link, peak_growth  # noqa: E402
from orchestrator.analysis.string_stability import interior_vehicle  # noqa: E402
from orchestrator.scenario.config import Config, config_from_mapping  # noqa: E402
from orchestrator.support.output import IMAGE, check_target, replacing  # noqa: E402
from orchestrator.sweep.plot import PlotError  # noqa: E402
from orchestrator.sweep.results import lookup, read_records  # noqa: E402  (the sweep folder's reading)

LAW, DELAY, LOSS = "platoon.speed_law", "links.delay", "links.loss"


def measured_gains(config: Config, trace_path: Path) -> tuple[np.ndarray, np.ndarray | None]:
    """Per probe frequency, per link that measures propagation: the run's gains, and the sampled-data
    cascade's prediction for the same links of the same run (None where it does not apply)."""
    from orchestrator.trace import load

    trace = load(trace_path)
    frequencies = probe_frequencies(config)
    names = trace.vehicles()
    order = clean_order(config, names)
    if not frequencies or len(order) < 2:
        raise PlotError(f"{trace_path}: its config has no sinusoid, or too few vehicles past the pushed ones")
    window = steady_window(config, float(trace.component(order[0])["t"][-1]))
    measured = np.array(frequency_gains(vehicle_errors(trace, config), order, frequencies, window))
    predicted = predicted_gains(config, names, order, frequencies)
    return measured, None if predicted is None else np.array(predicted)


def _changed(point: dict[str, Any]) -> tuple[Config, int]:
    """A run's config as the analysis takes it (the same links), and its interior vehicle."""
    return point["config"], interior_vehicle(point["config"])


def _analytic(config: Config, delay: float, loss: float) -> tuple[float, float]:
    """(peak growth per link, largest growth at the probe frequencies) of the sampled-data cascade of
    ``config`` with every link's delay and loss set."""
    links = config.links.model_copy(update={"delay": delay, "loss": loss})
    changed = config.model_copy(update={"links": links})
    vehicle = interior_vehicle(changed)
    probes = growth_per_link(changed, vehicle, np.array(probe_frequencies(config))).max()
    return peak_growth(changed, vehicle).gain, float(probes)


def _points(folder: Path) -> list[dict[str, Any]]:
    points = []
    for record in read_records(folder):
        if record["status"] == "invalid":
            continue
        where = {key: lookup(record, key) for key in (LAW, DELAY, LOSS)}
        if any(value is None for value in where.values()):
            raise PlotError(f"run {record['id']}: no {', '.join(k for k, v in where.items() if v is None)} (not a "
                            "string-stability sweep: configs/sweeps/string_stability.toml)")
        config = config_from_mapping(record["config"])
        missing = exact_applies(config)
        if missing is not None:
            raise PlotError(f"run {record['id']}: the sampled-data cascade does not model {missing}")
        gain = deviation = math.nan
        if record["status"] == "completed":
            measured, predicted = measured_gains(config, folder / record["trace"])
            gain, deviation = float(measured.max()), float(np.abs(measured / predicted - 1.0).max())
        points.append({**where, "gain": gain, "deviation": deviation, "config": config})
    return points


def agreement_lines(points: list[dict[str, Any]], stable: dict[str, dict[tuple[float, float], bool]]) -> list[str]:
    """Per law: how far the measured gains are from the cascade's prediction for the same links (worst over
    links and probes, by loss rate), and in how many runs the headline verdict (largest measured gain above 1)
    is the closed form's."""
    lines = []
    for law, verdicts in stable.items():
        mine = [p for p in points if p[LAW] == law and not math.isnan(p["gain"])]
        worst = {loss: max(p["deviation"] for p in mine if p[LOSS] == loss) for loss in sorted({p[LOSS] for p in mine})}
        agree = sum((p["gain"] > 1.0) == (not verdicts[(p[DELAY], p[LOSS])]) for p in mine)
        by_loss = ", ".join(f"{100 * deviation:.2f} % at loss {loss:g}" for loss, deviation in worst.items())
        lines.append(f"{law}: measured vs the cascade, worst over links and probes: {by_loss}; headline verdict = "
                     f"closed form's in {agree} of {len(mine)} runs")
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


def _analytic_grid(config: Config, delays: np.ndarray, losses: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The cascade's peak growth and its largest growth at the probes over (loss, delay)."""
    peaks, probes = np.empty((len(losses), len(delays))), np.empty((len(losses), len(delays)))
    for i, loss in enumerate(losses):
        for j, delay in enumerate(delays):
            peaks[i, j], probes[i, j] = _analytic(config, float(delay), float(loss))
    return peaks, probes


def _panel(axis, mine: list[dict[str, Any]], grid: tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray], norm, cmap):
    delays, losses, peaks, probes = grid
    image = axis.pcolormesh(delays, losses, np.clip(peaks, norm.vmin, norm.vmax), norm=norm, cmap=cmap, shading="nearest")
    if peaks.min() < 1.0 + 1e-9 < peaks.max():
        axis.contour(delays, losses, peaks, levels=[1.0 + 1e-9], colors="black", linewidths=1.6)
    if probes.min() < 1.0 < probes.max():
        axis.contour(delays, losses, probes, levels=[1.0], colors="black", linewidths=1.0, linestyles="dashed")
    for p in mine:
        gain = p["gain"]
        colour = "white" if math.isnan(gain) else cmap(norm(min(max(gain, norm.vmin), norm.vmax)))
        axis.scatter(p[DELAY], p[LOSS], s=70, color=colour, edgecolors="black", zorder=3)
        label = "failed" if math.isnan(gain) else f"{gain:.3f}"
        axis.annotate(label, (p[DELAY], p[LOSS]), textcoords="offset points", xytext=(0, 8), ha="center", fontsize=6,
                      bbox={"boxstyle": "round,pad=0.1", "facecolor": "white", "alpha": 0.8, "linewidth": 0})
    ticks = sorted({p[DELAY] for p in mine})
    axis.set_xticks(ticks, [age_label(mine[0]["config"], t) for t in ticks], fontsize=6)
    return image


def draw_stability_map(folder: Path, png: Path, overwrite: bool = False, resolution: int = 11) -> tuple[Path, list[str]]:
    """Draw the map; return its path and ``agreement_lines`` (what the figure cannot show to 0.01 %)."""
    check_target(png, overwrite, [folder / "results.csv"], kind=IMAGE)  # before minutes of reading traces
    points = _points(folder)
    laws = list(dict.fromkeys(p[LAW] for p in points))
    delays = np.linspace(0.0, max(p[DELAY] for p in points), resolution)
    losses = np.linspace(0.0, max(p[LOSS] for p in points), resolution)
    stable = {law: {(p[DELAY], p[LOSS]): peak_growth(*_changed(p)).string_stable for p in points if p[LAW] == law}
              for law in laws}
    grids = {law: _analytic_grid(next(p for p in points if p[LAW] == law)["config"], delays, losses) for law in laws}
    # the scale ends at the analysis's highest peak: a lossy run's single-seed gain beyond it shows in its
    # label, its dot at the scale's end
    norm, cmap = colour_scale(max(float(peaks.max()) for peaks, _ in grids.values()))
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
    figure.suptitle("String stability: the sampled-data cascade's peak growth per link (colour; solid line: 1, "
                    "dashed: 1 at the probes)\nunder each run's measured largest gain per link at the probes (dot "
                    "and label; a lossy dot is one run of one seed)", fontsize=8)
    figure.colorbar(image, ax=axes[0].tolist(), label="gain per link", shrink=0.9, extend="max")
    try:  # the output rule (support/output.py): drawn aside, synced, renamed
        with replacing(png) as aside:
            figure.savefig(aside, format="png")
    finally:
        plt.close(figure)
    return png, agreement_lines(points, stable)
