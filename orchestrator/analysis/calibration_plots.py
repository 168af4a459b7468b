"""The figure of `platoon calibrate --plots DIR`: one robot's recorded motion against its model, before (the run's
own config) and after calibration: the path, the speed over the ground, the wheel speeds and the misfit."""

from __future__ import annotations

from pathlib import Path
from typing import Any, Sequence

import numpy as np

from orchestrator.analysis.calibrate import FINE_RATE, SEGMENTS, PathProblem, RobotCalibration, model_values
from orchestrator.analysis.compare import ground_speed
from orchestrator.analysis.robot_record import RobotRecord
from orchestrator.analysis.wheel_path import rigid_fit


def _model_path(problem: PathProblem, record: RobotRecord, window: np.ndarray, labels: np.ndarray,
                values: dict[str, float]) -> tuple[Any, np.ndarray, np.ndarray]:
    path = problem.path(record, window, values)
    x, y, _ = rigid_fit(path.x, path.y, record.x[window], record.y[window], labels)
    return path, x, y


def calibration_figures(records: Sequence[RobotRecord], calibration: RobotCalibration, directory: Path) -> list[Path]:
    """One PNG per record of the robot: ``DIR/robotK-vehicleN-TRACE.png``."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    directory.mkdir(parents=True, exist_ok=True)
    problem = PathProblem(records, SEGMENTS[1], rate=FINE_RATE)
    before = model_values(records[0].model)
    after = calibration.values()
    written = []
    for record, window, labels in zip(problem.records, problem.windows, problem.labels):
        t = record.stamp[window]
        fig, axes = plt.subplots(2, 2, figsize=(13, 9))
        (ax_path, ax_speed), (ax_wheels, ax_misfit) = axes
        ax_path.plot(record.x[window], record.y[window], ".", ms=1, color="0.5", label="recorded poses")
        recorded_speed = ground_speed(t, record.x[window], record.y[window])
        ax_speed.plot(t, recorded_speed, color="0.5", lw=0.8, label="recorded (poses, over 0.2 s)")
        for values, style, name in ((before, "tab:red", "model before"), (after, "tab:blue", "calibrated")):
            path, x, y = _model_path(problem, record, window, labels, values)
            misfit = np.hypot(x - record.x[window], y - record.y[window])
            rms = float(np.sqrt(np.mean(misfit ** 2)))
            cut = np.flatnonzero(np.diff(labels)) + 1  # the pieces apart: each is placed on the record on its own
            ax_path.plot(np.insert(x, cut, np.nan), np.insert(y, cut, np.nan), color=style, lw=0.8,
                         label=f"{name} ({rms * 1e3:.1f} mm rms)")
            ax_speed.plot(t, 0.5 * (path.right + path.left), color=style, lw=0.8, label=name)
            ax_wheels.plot(t, path.right, color=style, lw=0.8, label=f"{name}: right")
            ax_wheels.plot(t, path.left, color=style, lw=0.8, ls="--", label=f"{name}: left")
            ax_misfit.plot(t, misfit * 1e3, color=style, lw=0.6, label=name)
        c = record.commands
        ax_wheels.step(c.sent, c.right, where="post", color="0.4", lw=0.5, label="commanded right")
        ax_misfit.axhline(calibration.pose_noise * 1e3 * np.sqrt(2), color="0.3", ls=":",
                          label="the poses' own noise (rms distance)")
        ax_path.set(xlabel="x [m]", ylabel="y [m]", title="path (each 4 s piece placed on the record, as fitted)")
        ax_path.axis("equal")
        ax_speed.set(xlabel="t [s] since the first command", ylabel="speed [m/s]", title="speed over the ground")
        ax_wheels.set(xlabel="t [s]", ylabel="wheel speed [m/s]", title="the model's wheel speeds")
        ax_misfit.set(xlabel="t [s]", ylabel="distance [mm]", title="model to recorded pose", yscale="log")
        for ax in axes.flat:
            ax.legend(fontsize=7, loc="best")
            ax.grid(alpha=0.3)
        fig.suptitle(f"robot {record.robot} ({record.vehicle}, {Path(record.source).name}): residual "
                     f"{calibration.residual * 1e3:.2f} mm rms per axis after calibration, "
                     f"{calibration.residual_before * 1e3:.1f} mm before")
        fig.tight_layout()
        path = directory / f"robot{record.robot}-{record.vehicle}-{Path(record.source).stem}.png"
        fig.savefig(path, dpi=110)
        plt.close(fig)
        written.append(path)
    return written
