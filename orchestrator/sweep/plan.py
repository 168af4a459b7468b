"""The runs of a sweep: each one a list of ``--set`` overrides on the base config, with a stable id.

A run is exactly ``platoon run BASE --set KEY=VALUE ...`` (the sweep's ``[set]`` keys, then its
varied values), validated by the same ``load_config``. Its id is a hash of its varied values (and its
sample number for random draws), so the same point gets the same id, trace file and result file in
every invocation: that is what lets a sweep resume, and what makes two runs never share a file.

Random draws use ``random.Random(seed).random()``, whose sequence Python guarantees across versions;
samples are drawn one after the other, so raising ``samples`` keeps the earlier ones (and their ids).
"""

from __future__ import annotations

import hashlib
import itertools
import json
import math
import random
from dataclasses import dataclass
from typing import Any, Iterator

from orchestrator.scenario.config import Config, ConfigError, load_config, read_config_text
from orchestrator.scenario.limits import check_run_size
from .spec import RandomRange, Scalar, SweepError, SweepSpec

ID_LENGTH = 12  # hex digits of the run id: collisions are out of reach for any sweep a person runs


@dataclass(frozen=True)
class Run:
    """One point of the sweep. ``config`` is None when the config rejects this point (``error`` says why)."""

    id: str
    values: dict[str, Scalar]  # varied key -> value (plus "sample" for random draws)
    overrides: list[str]  # KEY=VALUE as platoon run --set takes them
    config: Config | None
    raw: dict[str, Any] | None  # the config mapping the run validates (sent to the worker)
    text: str  # the TOML recorded in the trace: the base file, then the overrides as a comment
    config_hash: str  # of the resolved config: a result made with another one is not this run's
    error: str | None = None


def toml_literal(value: Scalar) -> str:
    """``value`` as the TOML text ``--set KEY=VALUE`` parses back to the same value."""
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, float):
        return repr(value) if math.isfinite(value) else ("nan" if math.isnan(value) else ("inf" if value > 0 else "-inf"))
    if isinstance(value, int):
        return str(value)
    return json.dumps(value)  # a TOML basic string (JSON escapes are TOML escapes)


def run_id(values: dict[str, Scalar]) -> str:
    canonical = json.dumps(values, sort_keys=True, separators=(",", ":"))
    return hashlib.sha256(canonical.encode()).hexdigest()[:ID_LENGTH]


def _draw(bounds: RandomRange, rng: random.Random) -> int | float:
    u = rng.random()
    if bounds.integer:
        return min(int(bounds.low) + math.floor(u * (bounds.high - bounds.low + 1)), int(bounds.high))
    return bounds.low + u * (bounds.high - bounds.low)


def points(spec: SweepSpec) -> Iterator[dict[str, Scalar]]:
    """Every point, one at a time: the grid's combinations (first key slowest), each with every random
    sample. Streamed: memory does not grow with the number of points (the draws are made again for
    each combination, from the same seed, so each combination gets the same samples)."""
    combos = (dict(zip(spec.grid, values)) for values in itertools.product(*spec.grid.values()))
    for combo in combos if spec.grid else iter([{}]):
        if not spec.ranges:
            yield combo
            continue
        rng = random.Random(spec.seed)
        for index in range(spec.samples):
            yield {**combo, "sample": index, **{key: _draw(bounds, rng) for key, bounds in spec.ranges.items()}}


def value_columns(spec: SweepSpec) -> list[str]:
    """The keys of each point's values, in their order (results.csv's columns after ``id``)."""
    return [*spec.grid, *(["sample", *spec.ranges] if spec.ranges else [])]


def count(spec: SweepSpec) -> int:
    """How many points ``spec`` has, without making them."""
    return math.prod(len(values) for values in spec.grid.values()) * (spec.samples if spec.ranges else 1)


def config_hash(config: Config) -> str:
    return hashlib.sha256(config.model_dump_json().encode()).hexdigest()


def plan(spec: SweepSpec) -> list[Run]:
    """Every run of ``spec`` in a list (small sweeps, tests); ``runs`` streams them."""
    return list(runs(spec))


def runs(spec: SweepSpec) -> Iterator[Run]:
    """The runs of ``spec`` in order, each validated as it is made; raises ``SweepError`` for a base that
    does not load or a key no config has. Ids never repeat: grid values are distinct (spec.py refuses a
    value listed twice) and random draws carry their sample number."""
    fixed = [f"{key}={toml_literal(value)}" for key, value in spec.fixed.items()]
    try:
        load_config(spec.base, fixed)
    except ConfigError as error:
        what = f"base {spec.base}" + (" with [set]" if fixed else "")
        raise SweepError(f"sweep file {spec.path}: {what}: {error}") from None
    base_text = read_config_text(spec.base)  # as load_config read it (a byte-order mark dropped)
    for values in points(spec):
        yield _run(spec, base_text, fixed, values)


def _run(spec: SweepSpec, base_text: str, fixed: list[str], values: dict[str, Scalar]) -> Run:
    overrides = fixed + [f"{key}={toml_literal(value)}" for key, value in values.items() if key != "sample"]
    identifier = run_id(values)
    text = f"{base_text.rstrip()}\n\n# platoon sweep {spec.path}, run {identifier}: --set " + " --set ".join(overrides) + "\n"
    try:
        config, raw = load_config(spec.base, overrides)
        check_run_size(config)  # an absurdly long run is rejected like an invalid one (no --allow-long here)
    except ConfigError as error:
        if "unknown key" in str(error):  # a key of the sweep file that no config has: every run would fail
            raise SweepError(f"sweep file {spec.path}: {error}") from None
        message = f"config: {error}"
        rejected = "invalid-" + hashlib.sha256(message.encode()).hexdigest()  # same error: same result
        return Run(identifier, values, overrides, None, None, text, rejected, message)
    return Run(identifier, values, overrides, config, raw, text, config_hash(config))
