"""A config before validation: its text, ``--set`` overrides applied to its raw TOML mapping, and the
defaults of the keys that size a run.

Kept apart from the validated models (config.py) because it needs no pydantic: `platoon run` reads a
config's size here, before pydantic and the models load, to decide whether to start its trace writer
process at once (orchestrator/cli/trace_forecast.py). config.py re-exports what it always offered.
"""

from __future__ import annotations

import math
import tomllib
from pathlib import Path
from typing import Any

# Defaults of the keys that decide how much a run records (config.py's fields use these very values).
DEFAULT_STOP_TIME = 100.0  # s, simulation.stop_time
DEFAULT_STEP = 0.01  # s, simulation.step
DEFAULT_TRACE_EVERY = 1  # simulation.trace_every
DEFAULT_COUNT = 4  # platoon.count
FILE_KEYS = ("zenoh_config",)  # keys of [vehicles.K] that name a file


class ConfigError(ValueError):
    """A configuration problem, phrased for the person who wrote the config."""


def step_count(stop_time: float, step: float) -> int:
    """Number of communication steps; the last one ends at stop_time (to rounding)."""
    return max(1, int(math.floor(stop_time / step + 1e-9)))


def recorded_rows(steps: int, every: int) -> int:
    """Rows a run of ``steps`` steps records with ``simulation.trace_every`` = ``every``: its start, then
    every ``every``-th communication point."""
    return steps // every + 1


# A --set value that starts like one of these is TOML and must parse as exactly one value; anything
# else (a bare word such as regular) is taken as a string.
_TOML_START = tuple("\"'[{+-0123456789")
_TOML_WORDS = ("true", "false", "inf", "nan")


def parse_value(text: str) -> Any:
    """A ``--set`` value: one TOML value (7, 0.5, true, "x", [1, 2]); a bare word is a string.

    The value is parsed inside an inline table, where TOML allows neither a comment nor a second
    statement, so ``3 x=1``, ``3 # note`` or ``3`` followed by a newline and more TOML is an error
    instead of a 3 with the rest silently dropped.
    """
    stripped = text.strip()
    word = stripped.split(None, 1)[0].rstrip(",]}") if stripped else ""
    looks_like_toml = stripped.startswith(_TOML_START) or word in _TOML_WORDS
    if not stripped:
        return ""
    try:
        parsed = tomllib.loads(f"value = {{v = {stripped}}}")
    except tomllib.TOMLDecodeError:
        if looks_like_toml or "\n" in stripped:
            raise ConfigError(f"{stripped!r} is not one TOML value (more after the value, a comment, or a typo?); "
                              "a string with spaces or quotes needs TOML quotes: 'KEY=\"...\"'") from None
        return stripped
    if list(parsed) != ["value"] or list(parsed["value"]) != ["v"]:
        raise ConfigError(f"{stripped!r} is not one TOML value: more TOML after it")
    return parsed["value"]["v"]


def apply_override(raw: dict[str, Any], assignment: str) -> None:
    """Apply ``KEY=VALUE`` (dotted key) to the raw config mapping."""
    if "=" not in assignment:
        raise ConfigError(f"--set {assignment!r}: expected KEY=VALUE, e.g. platoon.count=7")
    key, text = assignment.split("=", 1)
    parts = key.strip().split(".")
    if not all(parts):
        raise ConfigError(f"--set {assignment!r}: {key!r} is not a dotted key like platoon.count")
    node = raw
    for index, part in enumerate(parts[:-1]):
        child = node.setdefault(part, {})
        if not isinstance(child, dict):
            raise ConfigError(f"--set {assignment!r}: {'.'.join(parts[: index + 1])} is not a table")
        node = child
    try:
        node[parts[-1]] = parse_value(text)
    except ConfigError as error:
        raise ConfigError(f"--set {assignment!r}: {error}") from None


def read_config_text(path: str | Path) -> str:
    """The config file's text: UTF-8, with a byte-order mark accepted and dropped (Windows editors write
    one; it is not part of the TOML)."""
    try:
        data = Path(path).read_bytes()
    except OSError as error:
        raise ConfigError(f"cannot read the file: {error.strerror or error}") from None
    try:
        return data.decode("utf-8-sig")
    except UnicodeDecodeError as error:
        line = data[: error.start].count(b"\n") + 1
        raise ConfigError(f"not UTF-8 text: byte 0x{data[error.start]:02x} at line {line} (TOML files are UTF-8; "
                          "save it as UTF-8)") from None


def resolve_named_files(raw: dict[str, Any], folder: Path) -> None:
    """Make the files a config file names relative to that file's ``folder`` (not to the current folder:
    a config runs the same from anywhere). Values given with ``--set`` stay relative to the current
    folder, as every path typed on a command line."""
    hil = raw.get("hil")
    if isinstance(hil, dict) and isinstance(hil.get("lab_key"), str) and hil["lab_key"]:
        hil["lab_key"] = str(folder / Path(hil["lab_key"]).expanduser())  # an absolute one stays as it is
    vehicles = raw.get("vehicles")
    if not isinstance(vehicles, dict):
        return  # validation names the problem
    for table in vehicles.values():
        if not isinstance(table, dict):
            continue
        for key in FILE_KEYS:
            value = table.get(key)
            if isinstance(value, str) and value and not Path(value).is_absolute():
                table[key] = str(folder / value)


def raw_mapping(text: str, default_name: str, overrides: list[str] | tuple[str, ...] = (),
                folder: Path | None = None) -> dict[str, Any]:
    """A config's text parsed, named, its files resolved (``folder``: the config file's, see
    ``resolve_named_files``) and ``overrides`` applied: what validation reads (config.py, ``parse_config``)."""
    try:
        raw = tomllib.loads(text)
    except tomllib.TOMLDecodeError as error:
        raise ConfigError(f"not valid TOML: {error}") from None
    raw.setdefault("name", default_name)
    if folder is not None:
        resolve_named_files(raw, folder)
    for assignment in overrides:
        apply_override(raw, assignment)
    return raw
