"""Validated configs kept for the next command: a `platoon run` or `platoon report` of a config seen before
starts without pydantic.

Importing pydantic and building the config's models is about half of a short run's start-up and a third of a
report's (docs/performance.md, "Start-up"), for a verdict that only changes when the config or the code does.
So once pydantic has validated a config, its values are stored under the user's cache folder
(``$XDG_CACHE_HOME/platoon-cosim/configs``), keyed by the config's raw mapping (its TOML with ``--set`` applied,
its name and its files resolved: everything validation reads). The next time the same mapping comes, and no
file of the code loaded when it was stored changed (size and modification time of every module outside the
standard library: these models, pydantic, the FMU model's constants), the config is rebuilt from those values
as plain records that answer as the models do: the same values in the same fields, the same methods
(config_logic.py), the same ``model_dump``, ``model_copy`` and, for the whole config, the same
``model_dump_json`` text (which a trace stores). Only valid configs are stored: a config with an error is always
validated, so every message is pydantic's and config_errors.py's, as before. So are configs with live or remote
vehicles or ROS 2 publishing, whose paths were not written for records (they load pydantic anyway).

Before an entry is written, the records rebuilt from it are checked against the models they stand for (their
dumps and JSON texts equal); anything a record cannot hold exactly (a non-finite number, a tuple, another type)
is not stored. Standard library only, and no pydantic.
"""

from __future__ import annotations

import json
import math
import os
import sys
import zlib
from pathlib import Path
from typing import Any

from orchestrator.support.cache_files import cache_folder, loaded_files, stamps, write_whole

from .config_logic import LOGIC

FORMAT = 1  # of an entry; a new one makes every stored entry a miss
ENTRIES_KEPT = 256  # entries beyond this are removed, oldest first, when one is stored
_JSON_FORMS = {"": {}, "exclude_none": {"exclude_none": True}}  # the whole config's model_dump_json kept (the trace's)


class Unfit(Exception):
    """A config a record could not hold exactly: it is not stored (it is validated each time, as before)."""


class Record:
    """A table of a validated config, read back from the cache: its values as attributes, frozen.

    Each entry makes one subclass per model (named as the model, on its mixin from config_logic.py when it has
    one) with ``model_fields`` (the field names, in order), the model's defaults when every field has one, and
    ``_classes``: the entry's record classes by name."""

    model_fields: dict[str, None] = {}
    _defaults: dict[str, Any] | None = None
    _classes: dict[str, type["Record"]] = {}
    _json: dict[str, str] = {}

    def __init__(self, **values: Any) -> None:
        if self._defaults is not None:
            values = {**self._defaults, **values}
        for name in self.model_fields:
            object.__setattr__(self, name, values[name])

    def __setattr__(self, name: str, value: Any) -> None:
        raise AttributeError(f"{type(self).__name__} is frozen")

    def __eq__(self, other: object) -> bool:
        return type(other) is type(self) and self.__dict__ == other.__dict__

    def __hash__(self) -> int:
        return hash((type(self).__name__, *self.__dict__.values()))

    def __repr__(self) -> str:
        return f"{type(self).__name__}({', '.join(f'{name}={value!r}' for name, value in self.__dict__.items())})"

    def model_dump(self, exclude_none: bool = False) -> dict[str, Any]:
        return {name: _dump(value, exclude_none) for name, value in self.__dict__.items()
                if not (exclude_none and value is None)}

    def model_copy(self, update: dict[str, Any] | None = None) -> "Record":
        """A copy with ``update``'s fields replaced, unvalidated (as pydantic's ``model_copy``)."""
        copy = object.__new__(type(self))
        copy.__dict__.update(self.__dict__)
        copy.__dict__.update(update or {})
        return copy

    def model_dump_json(self, **options: Any) -> str:
        """The whole config's JSON text as pydantic wrote it, for the forms kept (``_JSON_FORMS``)."""
        form = next((name for name, kept in _JSON_FORMS.items() if kept == options), None)
        if form is None or form not in self._json:
            raise NotImplementedError(f"a cached config's model_dump_json({options}) was not kept (config_records.py)")
        return self._json[form]

    def _no_override(self) -> "Record":
        return self._classes["VehicleOverride"]()

    def _no_links(self) -> "Record":
        return self._classes["Links"]()


def _dump(value: Any, exclude_none: bool) -> Any:
    if isinstance(value, Record):
        return value.model_dump(exclude_none)
    if isinstance(value, list):
        return [_dump(item, exclude_none) for item in value]
    if isinstance(value, dict):
        return {key: _dump(item, exclude_none) for key, item in value.items()}
    return value


def _key(raw: dict[str, Any]) -> str:
    """The raw mapping as the entry holds it (TypeError or ValueError when it is not plain JSON)."""
    return json.dumps([FORMAT, sys.version, raw], allow_nan=False)


def _entry(key: str) -> Path:
    """The entry's file: named by two checksums of its key (zlib's, loaded anyway; OpenSSL's hashes cost a short
    run ~2 % to load), which the entry holds whole and is compared with, so two keys never share a verdict."""
    data = key.encode()
    return cache_folder("configs") / f"{zlib.crc32(data):08x}{zlib.adler32(data):08x}{len(data):x}.json"


def cached_config(raw: dict[str, Any]) -> Any:
    """The config validated from ``raw`` before, as records; None when there is none, or the code changed."""
    try:
        key = _key(raw)
        entry = json.loads(_entry(key).read_text(encoding="utf-8"))
        if entry["format"] != FORMAT or entry["key"] != key or entry["modules"] != stamps(entry["modules"]):
            return None
        return _records(entry)
    except (OSError, ValueError, KeyError, TypeError, AttributeError):
        return None


def store_config(raw: dict[str, Any], config: Any) -> None:
    """Keep ``config`` (pydantic's verdict on ``raw``) for the next command, if records can stand for it."""
    if config.live_vehicles() or config.remote_vehicles() or config.ros2.publish:
        return
    try:
        key = _key(raw)
        classes: dict[str, Any] = {}
        tree = _tree(config, classes)
        _tree(config._no_override(), classes)  # the default [vehicles.K], for a config without one
        specs: dict[str, Any] = {}
        while len(specs) < len(classes):  # a model's defaults may hold models of their own
            for name, model in list(classes.items()):
                specs.setdefault(name, _class_entry(model, classes))
        entry = {"format": FORMAT, "key": key, "config": tree, "classes": specs,
                 "json": {form: config.model_dump_json(**options) for form, options in _JSON_FORMS.items()}}
        entry["modules"] = stamps(loaded_files())
        text = json.dumps(entry, allow_nan=False)
        records = _records(json.loads(text))
        for exclude_none in (False, True):
            if records.model_dump(exclude_none) != config.model_dump(exclude_none=exclude_none):
                raise Unfit("the records do not dump as the models")
    except (Unfit, TypeError, ValueError):
        return
    write_whole(_entry(key), text)
    _prune(cache_folder("configs"))


def _class_entry(model: Any, classes: dict[str, Any]) -> dict[str, Any]:
    """A model's field names, and its defaults when every field has one."""
    required = any(info.is_required() for info in model.model_fields.values())
    return {"fields": list(model.model_fields),
            "defaults": None if required else _tree(model.model_construct(), classes)["="]}


def _tree(value: Any, classes: dict[str, Any]) -> Any:
    """``value`` as JSON: a model as {"@": its class name, "=": its fields}, a dict as {"#": ...}."""
    fields = getattr(type(value), "model_fields", None)
    if isinstance(fields, dict):
        name = type(value).__name__
        if classes.setdefault(name, type(value)) is not type(value):
            raise Unfit(f"two models named {name}")
        return {"@": name, "=": {field: _tree(getattr(value, field), classes) for field in fields}}
    if isinstance(value, dict):
        if not all(isinstance(key, str) for key in value):
            raise Unfit("a key that is not text")
        return {"#": {key: _tree(item, classes) for key, item in value.items()}}
    if type(value) is list:
        return [_tree(item, classes) for item in value]
    if type(value) is float and not math.isfinite(value):
        raise Unfit("a number that is not finite")
    if value is None or type(value) in (bool, int, float, str):
        return value
    raise Unfit(f"a value of type {type(value).__name__}")


def _records(entry: dict[str, Any]) -> Any:
    """The config of a stored ``entry``, as records."""
    classes: dict[str, type[Record]] = {}
    for name, spec in entry["classes"].items():
        bases = (LOGIC[name], Record) if name in LOGIC else (Record,)
        classes[name] = type(name, bases, {"model_fields": dict.fromkeys(spec["fields"]), "_classes": classes,
                                           "__module__": __name__})
    for name, spec in entry["classes"].items():
        if spec["defaults"] is not None:
            type.__setattr__(classes[name], "_defaults", {key: _value(item, classes) for key, item in spec["defaults"].items()})
    config = _value(entry["config"], classes)
    type.__setattr__(type(config), "_json", dict(entry["json"]))
    return config


def _value(tree: Any, classes: dict[str, type[Record]]) -> Any:
    if isinstance(tree, dict):
        if "@" in tree:
            record = object.__new__(classes[tree["@"]])
            record.__dict__.update({name: _value(item, classes) for name, item in tree["="].items()})
            return record
        return {key: _value(item, classes) for key, item in tree["#"].items()}
    if isinstance(tree, list):
        return [_value(item, classes) for item in tree]
    return tree


def _prune(folder: Path) -> None:
    """At most ``ENTRIES_KEPT`` entries: the oldest go first (a sweep by hand leaves one per --set)."""
    try:
        entries = [entry for entry in os.scandir(folder) if entry.name.endswith(".json")]
        if len(entries) <= ENTRIES_KEPT:
            return
        entries.sort(key=lambda entry: entry.stat().st_mtime_ns)
        for entry in entries[: len(entries) - ENTRIES_KEPT]:
            os.unlink(entry.path)
    except OSError:
        pass
