"""The paper's figure panels: speed, gap and path errors over time, and the X-Y plane.

One drawing function per panel, on a given matplotlib Axes: ``platoon report --plots`` puts each on
its own PNG (``write_plots``), ``platoon figure`` puts them side by side for two runs (figure.py).
Vehicle colours are the 3D scene's (``vehicle_colors``): tab10 up to 10 vehicles, else viridis with
a colour bar instead of a legend.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any, Callable, Iterable

import matplotlib

matplotlib.use("Agg")  # files only; never needs a display
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
from matplotlib.axes import Axes  # noqa: E402
from matplotlib.lines import Line2D  # noqa: E402
from matplotlib.patches import Patch  # noqa: E402

from orchestrator.scenario.config import Config  # noqa: E402
from orchestrator.analysis.metrics import path_errors  # noqa: E402
from orchestrator.trace import Trace  # noqa: E402
from orchestrator.trace.foxglove import LEGEND_UP_TO, vehicle_colors  # noqa: E402
from orchestrator.scenario.config_text import laws_text, links_text

Series = Callable[[Trace, Config, str], np.ndarray]

# (file stem, y label, title, the series of one vehicle): the three time panels of the paper's figures
TIME_PANELS: list[tuple[str, str, str, Series]] = [
    ("speed_errors", "speed error V - V_c [m/s]", "Speed errors",
     lambda trace, config, v: trace.component(v)["speed"] - config.platoon.speed),
    ("gap_errors", "gap error d - d* [m]", "Gap errors",
     lambda trace, config, v: trace.component(v)["gap"] - config.platoon.d_star),
    ("path_errors", "path error (signed distance) [m]", "Path errors",
     lambda trace, config, v: path_errors(config, trace.component(v)["x"], trace.component(v)["y"])),
]


def many(vehicles: list[str]) -> bool:
    """More vehicles than a legend can name: a colour bar tells them apart instead."""
    return len(vehicles) > LEGEND_UP_TO


def _label(name: str) -> str:
    return name.replace("vehicle", "vehicle ")


def draw_time_panel(axes: Axes, trace: Trace, config: Config, series: Series, ylabel: str, title: str) -> None:
    """One error over time, a line per vehicle, the disturbance windows as grey bands."""
    vehicles = trace.vehicles()
    for name, color in zip(vehicles, vehicle_colors(len(vehicles))):
        axes.plot(trace.component(name)["t"], series(trace, config, name), color=color, label=_label(name),
                  linewidth=1.0 if many(vehicles) else 1.3)
    for disturbance in config.disturbance:
        axes.axvspan(disturbance.start, disturbance.start + disturbance.duration, color="0.85", zorder=0)
    axes.set_xlabel("time [s]")
    axes.set_ylabel(ylabel)
    axes.set_title(title)
    axes.grid(True, alpha=0.4)


def time_legend_handles(axes: Axes, config: Config, vehicles: list[str]) -> list[Any]:
    """The legend's entries: each vehicle's line (unless a colour bar names them) and the disturbance band."""
    handles = [] if many(vehicles) else list(axes.get_lines())
    if config.disturbance:  # what struck, with its unit (the band shows when)
        label = "disturbance" + ("s" if len(config.disturbance) > 1 else "")
        handles.append(Patch(color="0.85", label=f"{label}: " + "; ".join(d.what() for d in config.disturbance)))
    return handles


def draw_xy(axes: Axes, trace: Trace, config: Config, title: str) -> list[Any]:
    """The X-Y plane: the path dashed, each vehicle's track, a dot where it ends, the target's end as a star.

    A straight line is drawn in path coordinates (distance along the line, signed distance off it)
    with the lateral axis stretched: at true aspect, deviations of centimetres on a kilometre vanish.
    Returns the legend's entries.
    """
    vehicles = trace.vehicles()
    colors = vehicle_colors(len(vehicles))
    target = trace.component("target")
    circle = config.path.kind == "circle"
    if circle:
        angles = np.linspace(0.0, 2.0 * np.pi, 400)
        axes.plot(config.path.center[0] + config.path.radius * np.cos(angles),
                  config.path.center[1] + config.path.radius * np.sin(angles), "k--", linewidth=1.0, zorder=5)
        axes.set_aspect("equal", adjustable="datalim")
        axes.set_xlabel("x [m]")
        axes.set_ylabel("y [m]")
    else:
        heading = config.path.heading
        ux, uy = np.cos(heading), np.sin(heading)
        cx, cy = config.path.center

        def along(x: np.ndarray, y: np.ndarray) -> np.ndarray:
            return (x - cx) * ux + (y - cy) * uy

        axes.axhline(0.0, color="k", linestyle="--", linewidth=1.0, zorder=5)
        axes.set_xlabel("distance along the line [m]")
        axes.set_ylabel("signed distance off the line [m] (stretched)")
    size = 3 if many(vehicles) else 5
    tracks = []
    for name, color in zip(vehicles, colors):
        channel = trace.component(name)
        x, y = channel["x"], channel["y"]
        if not circle:
            x, y = along(x, y), path_errors(config, x, y)
        tracks += axes.plot(x, y, color=color, linewidth=0.8 if many(vehicles) else 1.0, label=_label(name))
        axes.plot(x[-1], y[-1], "o", color=color, markersize=size, zorder=6)
    start = last_orbit_start(trace, config)
    if start is not None:
        tracks = _last_orbit(axes, trace, start, tracks)
        title += f"\n(the last orbit, from {start:.0f} s, solid; before it faint)"
    tx, ty = target["x"][-1:], target["y"][-1:]
    if not circle:
        tx, ty = along(tx, ty), path_errors(config, tx, ty)
    axes.plot(tx, ty, "k*", markersize=10, zorder=7)
    axes.set_title(title)
    axes.grid(True, alpha=0.4)
    handles = [] if many(vehicles) else tracks
    handles += [
        Line2D([], [], color="k", linestyle="--", label="path"),
        Line2D([], [], color="0.4", marker="o", linestyle="none", markersize=5, label="vehicle at the end"),
        Line2D([], [], color="k", marker="*", linestyle="none", markersize=10, label="virtual target at the end"),
    ]
    return handles


def last_orbit_start(trace: Trace, config: Config) -> float | None:
    """On a circle, the time the last orbit (2 pi R / V_c) starts when the run lasts over one and a half
    orbits (its X-Y tracks would be a tangle of rings); None otherwise."""
    if config.path.kind != "circle":
        return None
    t = trace.component(trace.vehicles()[0])["t"]
    orbit = 2.0 * np.pi * config.path.radius / config.platoon.speed
    return float(t[-1] - orbit) if len(t) and t[-1] - t[0] > 1.5 * orbit else None


def _last_orbit(axes: Axes, trace: Trace, start: float, tracks: list[Any]) -> list[Any]:
    """The whole tracks faded, the last orbit (from ``start``) drawn over them, where the steady offsets
    read as rings; returns the last orbit's lines (the legend's)."""
    solid = []
    for name, track in zip(trace.vehicles(), tracks):
        track.set_alpha(0.25)
        channel = trace.component(name)
        last = channel["t"] >= start
        solid += axes.plot(channel["x"][last], channel["y"][last], color=track.get_color(),
                           linewidth=track.get_linewidth() * 1.3, label=track.get_label())
    return solid


def colorbar(figure: Any, axes: Any, vehicles: list[str]) -> None:
    """A colour bar from vehicle 1 to vehicle N, the key of a platoon too large for a legend."""
    from matplotlib.cm import ScalarMappable
    from matplotlib.colors import ListedColormap, Normalize

    mappable = ScalarMappable(Normalize(1, len(vehicles)), ListedColormap(vehicle_colors(len(vehicles))))
    bar = figure.colorbar(mappable, ax=axes, fraction=0.03, pad=0.02)
    bar.set_label("vehicle (1 = leader)")


PLOT_STEMS = tuple(stem for stem, *_ in TIME_PANELS) + ("xy",)


def check_plot_targets(directory: Path, overwrite: bool = False, protect: Iterable[Path] = ()) -> list[Path]:
    """The panels' paths in ``directory``, each checked by the output rule (raises ``OutputError``, one
    line): `platoon report` calls it before reading the trace, so a refused target costs no reading."""
    from orchestrator.support.output import IMAGE, check_folder, check_target

    check_folder(directory, protect, "--plots")
    targets = [directory / f"{stem}.png" for stem in PLOT_STEMS]
    for target in targets:
        check_target(target, overwrite, protect, "--plots", kind=IMAGE)
    return targets


def write_plots(trace: Trace, config: Config, directory: Path, overwrite: bool = False,
                protect: Iterable[Path] = ()) -> list[Path]:
    """Write speed_errors.png, gap_errors.png, path_errors.png and xy.png into ``directory``, and links.png for a
    run with imperfect links.

    By the output rule (orchestrator/support/output.py): every target is checked before the first is
    drawn (an existing PNG is replaced, anything else only with ``overwrite``, an input never), and each
    is drawn aside and renamed into place; raises ``OutputError`` (one line) if one may not or cannot be.
    """
    from orchestrator.support.output import replacing

    targets = check_plot_targets(directory, overwrite, protect)
    vehicles = trace.vehicles()
    label = f"{config.name} ({laws_text(config)})"
    if links_text(config):  # a lossy run's panels say so, on a line of their own: "8 imperfect links (...)"
        label += f"\n{links_text(config)}"
    for target, (stem, ylabel, title, series) in zip(targets, TIME_PANELS):
        figure, axes = plt.subplots(figsize=(7.5, 4.2), dpi=120)
        draw_time_panel(axes, trace, config, series, ylabel, f"{title}: {label}")
        handles = time_legend_handles(axes, config, vehicles)
        if handles:
            axes.legend(handles=handles, loc="best", fontsize="small", ncol=2)
        if many(vehicles):
            colorbar(figure, axes, vehicles)
        else:
            figure.tight_layout()
        _save_png(figure, target, replacing)
    figure, axes = plt.subplots(figsize=(8.5, 6.5), dpi=120)
    handles = draw_xy(axes, trace, config, f"X-Y positions: {label}")
    axes.legend(handles=handles, loc="upper left", bbox_to_anchor=(1.01, 1.0), fontsize="small")
    if many(vehicles):
        colorbar(figure, axes, vehicles)
    figure.tight_layout()
    _save_png(figure, targets[-1], replacing)
    links = _link_panel(trace, config, directory, overwrite, protect, replacing)
    return targets + ([links] if links is not None else [])


def _link_panel(trace: Trace, config: Config, directory: Path, overwrite: bool, protect: Iterable[Path],
                replacing) -> Path | None:
    """links.png for a run with imperfect links: each link's age of information over time (the layout's
    links plot, docs/links.md), one line per link; None for a run whose links are all perfect."""
    from orchestrator.analysis.link_stats import AGE, is_link
    from orchestrator.support.output import IMAGE, check_target

    names = [name for name in trace.channels if is_link(name) and len(trace.component(name)["t"])]
    if not names:
        return None
    target = directory / "links.png"
    check_target(target, overwrite, protect, "--plots", kind=IMAGE)
    figure, axes = plt.subplots(figsize=(7.5, 4.2), dpi=120)
    for name in names:
        channel = trace.component(name)
        axes.plot(channel["t"], channel[AGE], linewidth=0.8, label=name.removeprefix("link_"))
    axes.set_xlabel("t [s]")
    axes.set_ylabel("age of information [s]")
    axes.set_title(f"age of the message each link delivers: {config.name}\n{links_text(config)}", fontsize=10)
    axes.legend(loc="upper left", bbox_to_anchor=(1.01, 1.0), fontsize="small")
    figure.tight_layout()
    _save_png(figure, target, replacing)
    return target


def _save_png(figure, target: Path, replacing) -> None:
    try:
        with replacing(target, "--plots") as aside:
            figure.savefig(aside, format="png")
    finally:
        plt.close(figure)
