"""The paper's figure pair from two traces: each run a column (the paper: regular law left, sine law
right), rows of speed, gap and path errors over time, then the X-Y plane.

The panels are orchestrator/analysis/plots.py's (one implementation each); this module only arranges them,
and adds one legend per column
(or a colour bar for platoons too large to name in a legend).
"""

from __future__ import annotations

from pathlib import Path

from typing import Any

import matplotlib

matplotlib.use("Agg")  # files only; never needs a display
import matplotlib.pyplot as plt  # noqa: E402
from matplotlib.figure import Figure  # noqa: E402

from orchestrator.scenario.config import Config  # noqa: E402
from orchestrator.analysis.plots import TIME_PANELS, colorbar, draw_time_panel, draw_xy, many, time_legend_handles  # noqa: E402
from orchestrator.trace import Trace  # noqa: E402


def column_title(config: Config, vehicles: int) -> str:
    """What tells the two columns apart: the law first, then the platoon and its path."""
    path = f"R = {config.path.radius:g} m circle" if config.path.kind == "circle" else "line"
    return f"{config.platoon.law} law: {vehicles} vehicles, {path}, d* = {config.platoon.d_star:g} m"


def draw_pair(runs: list[tuple[Trace, Config]]) -> Figure:
    """A figure with one column per run (two for the paper's pairs), four panels each."""
    columns = len(runs)
    figure, grid = plt.subplots(len(TIME_PANELS) + 1, columns, figsize=(6.2 * columns, 15.0), squeeze=False,
                                gridspec_kw={"height_ratios": [1.0] * len(TIME_PANELS) + [1.7]},
                                layout="constrained")
    for column, (trace, config) in enumerate(runs):
        vehicles = trace.vehicles()
        axes_column = grid[:, column]
        for row, (_, ylabel, title, series) in enumerate(TIME_PANELS):
            draw_time_panel(axes_column[row], trace, config, series, ylabel,
                            f"{column_title(config, len(vehicles))}\n{title}" if row == 0 else title)
        handles = time_legend_handles(axes_column[0], config, vehicles)
        xy_handles = draw_xy(axes_column[-1], trace, config, "X-Y positions")
        # one legend per column, under its X-Y panel, off the data: vehicles, disturbance band, marks
        seen = {handle.get_label() for handle in xy_handles}
        entries = xy_handles + [h for h in handles if h.get_label() not in seen]
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
