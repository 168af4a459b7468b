"""The sweep file: which base config, what is fixed, what varies (docs/sweeps.md).

```toml
base = "../paper/platoon.toml"        # relative to this sweep file's folder (runs the same from anywhere)
[set]                                 # optional: the same overrides for every run
"simulation.trace_every" = 10
[grid]                                # every combination of these values
"platoon.law" = ["sine", "regular"]
"platoon.count" = [2, 4, 8]
[random]                              # optional: samples drawn uniformly in [low, high]
samples = 20
seed = 1
ranges = { "platoon.k_v" = [0.2, 2.0] }   # two integers draw integers (both ends included)
```

Keys are the dotted config keys ``platoon run --set`` takes. Any problem raises ``SweepError`` with
one line naming the file and the key; the config keys themselves are checked when the runs are
planned (plan.py), by the same validation ``platoon run`` uses.
"""

from __future__ import annotations

import tomllib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from orchestrator.scenario.raw_config import ConfigError, read_config_text

Scalar = str | int | float | bool
# Columns of results.csv that a varied key must not shadow
RESERVED = ("id", "sample", "status", "error", "wall_time", "trace")


class SweepError(ValueError):
    """A problem with a sweep file or its output folder, phrased for the person who wrote it."""


@dataclass(frozen=True)
class RandomRange:
    low: int | float
    high: int | float

    @property
    def integer(self) -> bool:
        return isinstance(self.low, int) and isinstance(self.high, int)


@dataclass(frozen=True)
class SweepSpec:
    path: Path  # the sweep file
    base: Path
    fixed: dict[str, Scalar] = field(default_factory=dict)
    grid: dict[str, list[Scalar]] = field(default_factory=dict)
    samples: int = 0
    seed: int = 0
    ranges: dict[str, RandomRange] = field(default_factory=dict)

    @property
    def varied(self) -> list[str]:
        """The keys that vary, in the order of the file: grid first, then random."""
        return [*self.grid, *self.ranges]


def _is_scalar(value: Any) -> bool:
    return isinstance(value, (str, int, float, bool))


def _is_number(value: Any) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool)


def _check_key(where: str, key: str) -> None:
    parts = key.split(".")
    if not all(part.strip() == part and part for part in parts):
        raise SweepError(f"{where} {key!r}: expected a dotted config key like \"platoon.count\"")
    if key in RESERVED:
        raise SweepError(f"{where} {key!r}: a results.csv column has that name ({', '.join(RESERVED)})")


def _table(raw: dict[str, Any], name: str, where: str) -> dict[str, Any]:
    value = raw.get(name, {})
    if not isinstance(value, dict):
        raise SweepError(f"{where} [{name}]: expected a table, got {value!r}")
    return value


def load_sweep(path: str | Path) -> SweepSpec:
    """Read and check the sweep file ``path``."""
    path = Path(path)
    try:
        raw = tomllib.loads(read_config_text(path))  # UTF-8 (a byte-order mark dropped), as a config
    except ConfigError as error:
        raise SweepError(f"sweep file {path}: {error}") from None
    except tomllib.TOMLDecodeError as error:
        raise SweepError(f"sweep file {path}: not valid TOML: {error}") from None
    where = f"sweep file {path}:"
    unknown = sorted(set(raw) - {"base", "set", "grid", "random"})
    if unknown:
        raise SweepError(f"{where} {unknown[0]}: unknown key (expected base, [set], [grid], [random])")
    base = raw.get("base")
    if not isinstance(base, str) or not base:
        raise SweepError(f"{where} base: missing (required): the config file the runs start from")
    base_path = Path(path).parent / base  # relative to the sweep file, not to the current folder
    if not base_path.is_file():
        raise SweepError(f"{where} base = {base!r}: no such file {str(base_path)!r} (a path in a sweep file is "
                         "relative to the sweep file's folder)")

    fixed = _table(raw, "set", where)
    for key, value in fixed.items():
        _check_key(f"{where} set", key)
        if not _is_scalar(value):
            raise SweepError(f"{where} set {key!r} = {value!r}: expected a string, number or boolean")

    grid = _table(raw, "grid", where)
    for key, values in grid.items():
        _check_key(f"{where} grid", key)
        if not isinstance(values, list) or not values or not all(_is_scalar(v) for v in values):
            raise SweepError(f"{where} grid {key!r} = {values!r}: expected a non-empty list of strings, numbers or booleans")
        seen: set[tuple[type, Any]] = set()  # a set, not a list: a grid of 10^5 values is checked in linear time
        for value in values:
            if (type(value), value) in seen:  # 1 and 1.0 (or true) are different values; nan never repeats
                raise SweepError(f"{where} grid {key!r}: {value!r} is listed twice")
            seen.add((type(value), value))

    random = _table(raw, "random", where)
    unknown = sorted(set(random) - {"samples", "seed", "ranges"})
    if unknown:
        raise SweepError(f"{where} random.{unknown[0]}: unknown key (expected samples, seed, ranges)")
    samples, seed = random.get("samples", 0), random.get("seed", 0)
    ranges_raw = random.get("ranges", {})
    if random:
        if not isinstance(samples, int) or isinstance(samples, bool) or samples < 1:
            raise SweepError(f"{where} random.samples = {samples!r}: expected a whole number of at least 1")
        if not isinstance(seed, int) or isinstance(seed, bool):
            raise SweepError(f"{where} random.seed = {seed!r}: expected a whole number")
        if not isinstance(ranges_raw, dict) or not ranges_raw:
            raise SweepError(f"{where} random.ranges: expected a table of KEY = [low, high]")
    ranges: dict[str, RandomRange] = {}
    for key, bounds in ranges_raw.items():
        _check_key(f"{where} random.ranges", key)
        if not (isinstance(bounds, list) and len(bounds) == 2 and all(_is_number(b) for b in bounds)
                and bounds[0] <= bounds[1]):
            raise SweepError(f"{where} random.ranges {key!r} = {bounds!r}: expected [low, high], two numbers with low <= high")
        ranges[key] = RandomRange(bounds[0], bounds[1])

    for a_name, a, b_name, b in (("set", fixed, "grid", grid), ("set", fixed, "random.ranges", ranges),
                                 ("grid", grid, "random.ranges", ranges)):
        both = sorted(set(a) & set(b))
        if both:
            raise SweepError(f"{where} {both[0]!r} is both in {a_name} and in {b_name}")
    if not grid and not ranges:
        raise SweepError(f"{where} nothing varies: add a [grid] or a [random] table")
    return SweepSpec(path, base_path, dict(fixed), {k: list(v) for k, v in grid.items()}, samples if ranges else 0,
                     seed, ranges)
