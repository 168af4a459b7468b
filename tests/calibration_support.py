"""Robots for the calibration tests: truths drawn within the issue's bounds, and a synthetic live record made
by the model itself (``M3piDynamics.drive`` stepped with RK4 as the m3pi emulator steps it)."""

from __future__ import annotations

import random

import numpy as np

from fmus.model.dynamics import M3piDynamics
from fmus.model.integrate import integrate
from orchestrator.analysis.robot_record import RobotRecord, applied_between
from orchestrator.analysis.wheel_path import Commands

# issue 51's realistic bounds
BOUNDS = {"wheel_gain_right": (0.85, 1.15), "wheel_gain_left": (0.85, 1.15), "motor_time_constant": (0.03, 0.15),
          "wheel_speed_max": (0.6, 1.0), "wheel_deadband": (0.0, 0.05), "command_latency": (0.0, 0.04),
          "pose_latency": (0.0, 0.015)}
POSITION_NOISE, HEADING_NOISE = 0.002, 0.035  # the paper's ~2 mm and ~2 degrees


def random_truth(rng: random.Random) -> dict[str, float]:
    return {name: rng.uniform(low, high) for name, (low, high) in BOUNDS.items()}


def excitation(t: np.ndarray, full: bool = True) -> tuple[np.ndarray, np.ndarray]:
    """(left, right) wheel commands: speed steps, turns both ways and (``full``) a slow sweep through zero and a
    stretch past 1 m/s."""
    speed = 0.3 + 0.12 * np.sign(np.sin(2 * np.pi * t / 6.0))
    speed = np.where((t > 8) & (t < 16), 0.35 + 0.2 * np.sin(8.0 * (t - 8)), speed)  # the lag apart from the delay
    if full:
        speed = np.where((t > 20) & (t < 32), 0.2 - 0.2 * np.cos(2 * np.pi * (t - 20) / 6.0), speed)
        speed = np.where((t > 36) & (t < 38), 1.2, speed)
    turn = 0.08 * np.sin(2 * np.pi * t / 5.0)
    return np.clip(speed - turn, -1.2, 1.2), np.clip(speed + turn, -1.2, 1.2)


def synthetic_record(truth: dict[str, float], seconds: float = 45.0, seed: int = 0, noise: bool = True,
                     full: bool = True, echoes: bool = False) -> RobotRecord:
    """A record as a live run of robot ``truth`` would leave it: commands every 10 ms (with jitter), applied
    ``command_latency`` later; poses every 5 ms, noisy, each the robot ``pose_latency`` before its stamp (the
    latency a stamp does not show), received 1 ms after the stamp. With ``echoes``, each pose echoes the last
    command applied when it was taken, as the emulator's do (robot_record.applied_between reads them)."""
    rng = np.random.default_rng(seed)
    sent = np.arange(0.0, seconds, 0.01) + rng.uniform(0.0, 0.002, int(round(seconds / 0.01)))
    left, right = excitation(sent, full)
    left[-3:] = right[-3:] = 0.0
    dynamics = M3piDynamics(0.5, **{k: v for k, v in truth.items() if k in M3piDynamics.__dataclass_fields__})
    applied = sent + truth.get("command_latency", 0.0)
    stamps = np.arange(0.0, seconds + 0.5, 0.005)
    state, now, command = [0.0, 0.0, 0.3, 0.0, 0.0], 0.0, (0.0, 0.0)
    poses, echoed, k = [], [], 0
    for stamp in stamps - truth.get("pose_latency", 0.0):
        while k < len(applied) and applied[k] <= stamp:
            state = integrate(lambda _, s: dynamics.drive(s[2], s[3], s[4], command[1], command[0], 0.0), 0.0, state,
                              applied[k] - now, 0.001)
            now, command, k = applied[k], (left[k], right[k]), k + 1
        state = integrate(lambda _, s: dynamics.drive(s[2], s[3], s[4], command[1], command[0], 0.0), 0.0, state,
                          stamp - now, 0.001)
        now = stamp
        poses.append(state[:3])
        echoed.append(k)  # commands are numbered from 1: k is the number of the last one applied
    poses = np.array(poses)
    noise = rng.normal(0.0, 1.0, poses.shape) * [POSITION_NOISE, POSITION_NOISE, HEADING_NOISE] * noise
    earliest, latest = (applied_between(np.arange(1.0, len(sent) + 1.0), stamps, np.asarray(echoed, dtype=float))
                        if echoes else (None, None))
    commands = Commands(sent, sent + 0.1, left, right, earliest, latest)
    return RobotRecord("synthetic", "vehicle1", 1, 0.0, commands, stamps, stamps + 0.001,
                       *(poses + noise).T, M3piDynamics(0.5, wheel_speed_max=1.2))
