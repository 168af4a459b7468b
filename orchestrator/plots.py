"""The paper's figure panels as PNG: speed, gap and path errors over time, and the X-Y plane."""

from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")  # files only; never needs a display
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from .config import Config  # noqa: E402
from .metrics import path_errors  # noqa: E402
from .scenario import path_of  # noqa: E402
from .trace import Trace  # noqa: E402


def _time_panel(trace: Trace, values: dict[str, np.ndarray], ylabel: str, title: str, path: Path, config: Config) -> Path:
    figure, axes = plt.subplots(figsize=(7.5, 4.2), dpi=120)
    for name, series in values.items():
        axes.plot(trace.component(name)["t"], series, label=name.replace("vehicle", "vehicle "), linewidth=1.3)
    for disturbance in config.disturbance:
        axes.axvspan(disturbance.start, disturbance.start + disturbance.duration, color="0.85", zorder=0)
    axes.set_xlabel("time [s]")
    axes.set_ylabel(ylabel)
    axes.set_title(title)
    axes.grid(True, alpha=0.4)
    axes.legend(loc="best", fontsize="small", ncol=2)
    figure.tight_layout()
    figure.savefig(path)
    plt.close(figure)
    return path


def write_plots(trace: Trace, config: Config, directory: Path) -> list[Path]:
    """Write speed_errors.png, gap_errors.png, path_errors.png and xy.png into ``directory``."""
    directory.mkdir(parents=True, exist_ok=True)
    vehicles = trace.vehicles()
    law = config.platoon.law
    label = f"{config.name} ({law} law)"
    written = [
        _time_panel(trace, {v: trace.component(v)["speed"] - config.platoon.speed for v in vehicles},
                    "speed error V - V_c [m/s]", f"Velocity errors: {label}", directory / "speed_errors.png", config),
        _time_panel(trace, {v: trace.component(v)["gap"] - config.platoon.d_star for v in vehicles},
                    "distance error d - d* [m]", f"Distance errors: {label}", directory / "gap_errors.png", config),
        _time_panel(trace, {v: path_errors(config, trace.component(v)["x"], trace.component(v)["y"]) for v in vehicles},
                    "path error (signed distance) [m]", f"Path errors: {label}", directory / "path_errors.png", config),
    ]
    figure, axes = plt.subplots(figsize=(8.5, 6.5), dpi=120)
    path = path_of(config)
    target = trace.component("target")
    if config.path.kind == "circle":
        angles = np.linspace(0.0, 2.0 * np.pi, 400)
        axes.plot(config.path.center[0] + config.path.radius * np.cos(angles),
                  config.path.center[1] + config.path.radius * np.sin(angles), "k--", linewidth=1.2, label="path", zorder=5)
    else:
        s = np.linspace(np.min(target["arc_length"]) - 10 * config.platoon.d_star, np.max(target["arc_length"]), 2)
        points = np.array([path.pose_at(v)[:2] for v in s])
        axes.plot(points[:, 0], points[:, 1], "k--", linewidth=1.2, label="path", zorder=5)
    for name in vehicles:
        channel = trace.component(name)
        line, = axes.plot(channel["x"], channel["y"], linewidth=1.0, label=name.replace("vehicle", "vehicle "))
        axes.plot(channel["x"][-1], channel["y"][-1], "o", color=line.get_color())
    axes.plot(target["x"][-1], target["y"][-1], "k*", markersize=10, label="virtual target (end)")
    axes.set_aspect("equal", adjustable="datalim")
    axes.set_xlabel("x [m]")
    axes.set_ylabel("y [m]")
    axes.set_title(f"X-Y positions: {label}")
    axes.grid(True, alpha=0.4)
    axes.legend(loc="upper left", bbox_to_anchor=(1.01, 1.0), fontsize="small")
    figure.tight_layout()
    figure.savefig(directory / "xy.png")
    plt.close(figure)
    written.append(directory / "xy.png")
    return written
