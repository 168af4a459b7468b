"""The paper's figure pair from two traces: each run a column (the paper: regular law left, sine law
right), rows of speed, gap and path errors over time, then the X-Y plane.

The panels are orchestrator/analysis/plots.py's (one implementation each); this module only arranges them,
and adds one legend per column
(or a colour bar for platoons too large to name in a legend).
"""

from __future__ import annotations

import textwrap
from pathlib import Path
from typing import Any

import matplotlib

matplotlib.use("Agg")  # files only; never needs a display
import matplotlib.pyplot as plt  # noqa: E402
from matplotlib.figure import Figure  # noqa: E402

from orchestrator.scenario.config import Config  # noqa: E402
from orchestrator.analysis.plots import TIME_PANELS, colorbar, draw_time_panel, draw_xy, many, time_legend_handles  # noqa: E402
from orchestrator.trace import Trace  # noqa: E402
from orchestrator.scenario.config_text import laws_text

# characters per line of a legend entry: three columns of entries fit under a 6.2 in column in "small" type
LEGEND_LABEL_WIDTH = 28


def column_title(config: Config, vehicles: int) -> str:
    """What tells the two columns apart: the laws first, then the platoon and its path."""
    path = f"R = {config.path.radius:g} m circle" if config.path.kind == "circle" else "line"
    return f"{laws_text(config)}: {vehicles} vehicles, {path}, d* = {config.platoon.d_star:g} m"


def column_titles(runs: list[tuple[Trace, Config]]) -> list[str]:
    """Each column's header; when the runs' laws are the same (two traces of one law: a parameter or a
    disturbance compared), the laws no longer tell the columns apart, so each header names its trace."""
    titles = [column_title(config, len(trace.vehicles())) for trace, config in runs]
    if len(runs) > 1 and len({laws_text(config) for _, config in runs}) == 1:
        names = [trace.path.name for trace, _ in runs]
        if len(set(names)) < len(names):  # the same file name in two folders: the paths tell them apart
            names = [str(trace.path) for trace, _ in runs]
        titles = [f"{name}\n{title}" for name, title in zip(names, titles)]
    return titles


def draw_pair(runs: list[tuple[Trace, Config]]) -> Figure:
    """A figure with one column per run (two for the paper's pairs), four panels each; each row of error
    panels over one y range, so that the columns compare at a glance (the same height is the same error)."""
    columns = len(runs)
    figure, grid = plt.subplots(len(TIME_PANELS) + 1, columns, figsize=(6.2 * columns, 15.0), squeeze=False,
                                gridspec_kw={"height_ratios": [1.0] * len(TIME_PANELS) + [1.7]},
                                layout="constrained")
    for row in range(len(TIME_PANELS)):
        for column in range(1, columns):
            grid[row, column].sharey(grid[row, 0])  # autoscaled to the union of the row's data
    for column, ((trace, config), header) in enumerate(zip(runs, column_titles(runs))):
        vehicles = trace.vehicles()
        axes_column = grid[:, column]
        for row, (_, ylabel, title, series) in enumerate(TIME_PANELS):
            draw_time_panel(axes_column[row], trace, config, series, ylabel,
                            f"{header}\n{title}" if row == 0 else title)
        handles = time_legend_handles(axes_column[0], config, vehicles)
        xy_handles = draw_xy(axes_column[-1], trace, config, "X-Y positions")
        # one legend per column, under its X-Y panel, off the data: vehicles, disturbance band, marks
        seen = {handle.get_label() for handle in xy_handles}
        entries = xy_handles + [h for h in handles if h.get_label() not in seen]
        for entry in entries:  # a long label (what a disturbance struck) would widen the legend past its column
            entry.set_label(textwrap.fill(entry.get_label(), LEGEND_LABEL_WIDTH))
        axes_column[-1].legend(handles=entries, loc="upper center", bbox_to_anchor=(0.5, -0.12),
                               ncol=3, fontsize="small", frameon=False)
        if many(vehicles):
            colorbar(figure, list(axes_column), vehicles)
    _same_ranges([grid[-1, column] for column, (_, config) in enumerate(runs) if config.path.kind == "circle"])
    return figure


def _same_ranges(panels: list[Any]) -> None:
    """The X-Y panels of circles over the same ranges (the union of their data), so the columns compare
    at a glance; as data limits, which their equal aspect may widen alike, not fixed limits."""
    if len(panels) < 2:
        return
    x0 = min(a.dataLim.x0 for a in panels)
    x1 = max(a.dataLim.x1 for a in panels)
    y0 = min(a.dataLim.y0 for a in panels)
    y1 = max(a.dataLim.y1 for a in panels)
    for a in panels:
        a.update_datalim([(x0, y0), (x1, y1)])
        a.autoscale_view()


def save(figure: Figure, out: Path, dpi: int = 150) -> Path:
    """Write ``figure`` as PDF, SVG (vector) or PNG (``dpi``) by ``out``'s suffix, then release it."""
    from orchestrator.support.output import replacing

    try:  # the output rule: drawn aside, synced, renamed into place; OutputError (one line) if it cannot be
        with replacing(out) as aside:
            figure.savefig(aside, dpi=dpi if out.suffix.lower() == ".png" else None, format=out.suffix.lower()[1:])
    finally:
        plt.close(figure)
    return out
