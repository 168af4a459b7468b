"""``platoon sweep-plot``: a sweep's results as maps, |value| over two parameters, a panel per a third.

The defaults draw the shipped campaign (configs/sweeps/offset_map.toml): the last vehicle's steady
path offset against d*/R and platoon length, the regular law's panel beside the sine law's, on one
logarithmic colour scale (the sine law's offsets are ~1e-9 m, the regular law's metres). Each cell
says the signed value; a run that failed is marked so, and so is one that left the model (a collision,
a pass, an impossible speed: its ``run.left_model``), whose value is no model's and is not drawn.

The rows are those of DIR/results.csv; axes may name any config key, varied or not, read from each
run's resolved config (DIR/results/<id>.json), or ``d_star/R`` (platoon.d_star / path.radius): results.py
reads them.
"""

from __future__ import annotations

import json
import math
import textwrap
from pathlib import Path
from typing import Any

import matplotlib

matplotlib.use("Agg")  # files only; never needs a display
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
from matplotlib.colors import LogNorm  # noqa: E402

from orchestrator.support.output import IMAGE, check_target, replacing  # noqa: E402
from orchestrator.analysis.metrics import SUMMARY_UNITS  # noqa: E402
from orchestrator.analysis.validity import LEFT_MODEL  # noqa: E402
from orchestrator.scenario.config import key_unit  # noqa: E402

from .results import RATIO, ResultsError, lookup, read_records  # noqa: E402  (the sweep folder's reading)



class PlotError(ResultsError):
    """The folder or the options cannot make a map; the message names which."""


def _shared(records: list[dict[str, Any]], keys: list[str]) -> dict[str, Any]:
    """The keys of ``keys`` that every run with a config has at one value (not varied), and that value."""
    shared = {}
    for key in keys:
        found = {json.dumps(lookup(r, key)) for r in records if r.get("config") is not None}
        if len(found) == 1:
            shared[key] = json.loads(found.pop())
    return shared


def _label(value: Any) -> str:
    return f"{value:.3g}" if isinstance(value, float) else str(value)


def _axis_name(key: str) -> str:
    """An axis's config key with its unit: ``platoon.k_v [1/s]`` (d*/R and counts have none)."""
    if key == RATIO:
        return "d*/R"
    unit = key_unit(key)
    return f"{key} [{unit}]" if unit else key


def draw_map(folder: Path, value: str, x: str, y: str, panel: str, png: Path, overwrite: bool = False) -> Path:
    everything = read_records(folder)
    inputs = [folder / "results.csv", folder / "results.parquet", *(folder / "results" / f"{r['id']}.json" for r in everything)]
    check_target(png, overwrite, inputs, kind=IMAGE)  # before drawing: a refused --out costs nothing
    records = everything  # an invalid point (its config refused) is a cell too: it says "invalid", never blank
    columns = {name for r in records for name in r["metrics"]}
    if value not in columns and any(r["status"] == "completed" for r in records):
        raise PlotError(f"--value {value}: not a result column (e.g. {', '.join(sorted(columns)[:4])}, last.path_offset)")
    if value == LEFT_MODEL:
        raise PlotError(f"--value {value}: a text column (where a run left the model), marked on every map")
    cells: dict[tuple[Any, Any, Any], float] = {}
    invalid: set[tuple[Any, Any, Any]] = set()
    left: set[tuple[Any, Any, Any]] = set()  # runs that left the model (orchestrator/analysis/validity.py)
    axes_options = {"--panel": panel, "--y": y, "--x": x}
    shared = _shared(records, list(axes_options.values()))
    for record in records:
        where = tuple(lookup(record, key) for key in axes_options.values())
        if record["status"] == "invalid":  # a refused config has no resolved keys: the runs' common value stands
            where = tuple(shared.get(key) if found is None else found for key, found in zip(axes_options.values(), where))
            if None in where:
                continue
            invalid.add(where)
        for (option, key), found in zip(axes_options.items(), where):
            if found is None:
                raise PlotError(f"{option} {key}: no such config key in run {record['id']}")
        if where in cells:
            varied = ", ".join(record["values"])
            raise PlotError(f"several runs fall on {panel}={where[0]}, {y}={where[1]}, {x}={_label(where[2])}: "
                            f"choose --x, --y and --panel among the varied keys ({varied}) so that one run fills each cell")
        if record["metrics"].get(LEFT_MODEL):  # a run that left the model is marked, its value not drawn
            left.add(where)
        metric = record["metrics"].get(value) if record["status"] == "completed" and where not in left else None
        cells[where] = float(metric) if metric is not None else math.nan
    panels = list(dict.fromkeys(key[0] for key in cells))
    ys = sorted({key[1] for key in cells})
    xs = sorted({key[2] for key in cells})
    magnitudes = [abs(v) for v in cells.values() if math.isfinite(v) and v != 0.0]
    low, high = (min(magnitudes), max(magnitudes)) if magnitudes else (1e-12, 1.0)
    norm = LogNorm(vmin=low, vmax=max(high, low * 10))

    figure, axes = plt.subplots(1, len(panels), figsize=(0.8 + 0.85 * len(xs) * len(panels) + 1.2, 1.6 + 0.55 * len(ys)),
                                dpi=120, squeeze=False, sharey=True, layout="constrained")
    image = None
    for axis, name in zip(axes[0], panels):
        grid = np.full((len(ys), len(xs)), math.nan)
        for (p, yv, xv), v in cells.items():
            if p == name:
                grid[ys.index(yv), xs.index(xv)] = v
        shown = np.ma.masked_invalid(np.clip(np.abs(grid), norm.vmin, None))
        image = axis.imshow(shown, norm=norm, cmap="viridis", origin="lower", aspect="auto")
        for row in range(len(ys)):
            for column in range(len(xs)):
                v = grid[row, column]
                missing = (name, ys[row], xs[column]) not in cells
                cell = (name, ys[row], xs[column])
                text = ("" if missing else "invalid" if cell in invalid else "left\nmodel" if cell in left
                        else "failed" if math.isnan(v) else f"{v:.2g}")
                bright = not math.isnan(v) and norm(max(abs(v), norm.vmin)) > 0.6
                axis.text(column, row, text, ha="center", va="center", fontsize=7, color="black" if bright else "white")
        axis.set_facecolor("0.35")
        axis.set_xticks(range(len(xs)), [_label(v) for v in xs])
        axis.set_yticks(range(len(ys)), [_label(v) for v in ys])
        axis.set_xlabel(_axis_name(x))
        panel_unit = key_unit(panel) if panel != RATIO else None
        axis.set_title(f"{panel} = {name}" + (f" {panel_unit}" if panel_unit else ""))
    axes[0][0].set_ylabel(_axis_name(y))
    unit = SUMMARY_UNITS.get(value.rsplit(".", 1)[-1])  # the report's quantities have units; other columns none
    unit_text = f" [{unit}]" if unit else ""
    title = f"{value}{unit_text}: signed value in each cell, its magnitude in colour"
    # wrapped to the figure's width: a small grid makes a narrow figure, and a long line would be cut at both ends
    characters = max(16, int(figure.get_figwidth() * 72 / (0.6 * plt.rcParams["font.size"] * 1.2)))
    figure.suptitle(textwrap.fill(title, characters))
    figure.colorbar(image, ax=axes[0].tolist(), label=f"|{value}|{unit_text}", shrink=0.9)
    try:  # the output rule (support/output.py): drawn aside, synced, renamed; OutputError in one line
        with replacing(png) as aside:
            figure.savefig(aside, format="png")
    finally:
        plt.close(figure)
    return png
