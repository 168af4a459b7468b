"""Configs that are valid but probably not what the user meant: a warning each, never an error.

Such a config runs (someone may want exactly that), so these are not validation rules
(orchestrator/scenario/config.py); `platoon run`, `analyze`, `export-ssp` and `m3pi-emulator` print each as one
``warning:`` line naming the numbers and the keys to change.
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from orchestrator.scenario.config import Config


def config_warnings(config: Config) -> list[str]:
    """One sentence per suspicious setting, in the order of the config's tables."""
    return [text for text in (_longer_than_path(config), _m3pi_too_slow(config)) if text]


def _longer_than_path(config: Config) -> str | None:
    """A platoon whose spacings add up to more than the circle: its last vehicles drive among the first."""
    if config.path.kind != "circle":
        return None
    count, d_star = config.platoon.count, config.platoon.d_star
    circumference = 2.0 * math.pi * config.path.radius
    if count * d_star <= circumference:
        return None
    return (f"the platoon is longer than its path: platoon.count x platoon.d_star = {count} x {d_star:g} m = "
            f"{count * d_star:g} m > the circle's circumference 2 pi path.radius = {circumference:.4g} m, so its "
            "last vehicles drive among the first; lower platoon.count or platoon.d_star, or raise path.radius")


def _m3pi_too_slow(config: Config) -> str | None:
    """m3pi robots asked to follow a speed their wheels cannot reach (V = mean of the two wheel speeds)."""
    speed = config.platoon.speed
    robots = [i for i in config.m3pi_vehicles() if config.m3pi_of(i).wheel_speed_max < speed]
    if not robots:
        return None
    limit = config.m3pi_of(robots[0]).wheel_speed_max
    which = f"vehicle {robots[0]} is an m3pi" if len(robots) == 1 else f"{len(robots)} vehicles are m3pi robots"
    return (f"{which}, whose wheels top out at m3pi.wheel_speed_max = {limit:g} m/s, below platoon.speed = "
            f"{speed:g} m/s: it cannot keep up, and its speed can fall to zero, which ends the run; "
            "lower platoon.speed (an m3pi platoon: configs/paper/m3pi.toml) or raise m3pi.wheel_speed_max")
