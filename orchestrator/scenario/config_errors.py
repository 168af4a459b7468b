"""pydantic's validation errors rewritten as one line naming the key, the value and what was expected (with
the declared range and unit of a numeric key, and the nearest known key for a misspelt one), and the unit of
any key for labels. It reads the declarations of the root model it is given."""

from __future__ import annotations

from typing import Annotated, Any, Union, get_args, get_origin

import annotated_types
from pydantic import BaseModel, ValidationError

from orchestrator.support.suggest import did_you_mean

from .config_types import NAME_RULE, Unit, UnitNote, Expected, RuleError
from .ros2_config import Ros2Rule

def _key_of(loc: tuple[Any, ...]) -> str:
    key = ""
    for part in loc:
        if isinstance(part, int):
            key += f"[{part}]"
        else:
            key += ("." if key else "") + str(part)
    return key


_RANGE_ERRORS = {"finite_number", "greater_than", "greater_than_equal", "less_than", "less_than_equal"}
_BOUND_WORDS = (("gt", ">"), ("ge", ">="), ("lt", "<"), ("le", "<="))


def _field_at(root: type[BaseModel], loc: tuple[Any, ...]) -> tuple[Any, list[Any]]:
    """(type, constraint objects) of the key at pydantic location ``loc`` of ``root``, from the declarations."""
    annotation: Any = root
    metadata: list[Any] = []
    for part in loc:
        annotation, metadata = _unwrap(annotation)
        origin = get_origin(annotation)
        if isinstance(annotation, type) and issubclass(annotation, BaseModel) and part in annotation.model_fields:
            info = annotation.model_fields[part]
            annotation, metadata = info.annotation, list(info.metadata)
        elif origin in (list, dict):
            annotation, metadata = get_args(annotation)[-1], []
        else:
            break
    annotation, more = _unwrap(annotation)
    return annotation, metadata + more


def _unwrap(annotation: Any) -> tuple[Any, list[Any]]:
    """Strip ``X | None`` and ``Annotated[X, ...]``, collecting the annotated constraints."""
    metadata: list[Any] = []
    while True:
        if get_origin(annotation) is Union or type(annotation).__name__ == "UnionType":
            annotation = next(a for a in get_args(annotation) if a is not type(None))
        elif get_origin(annotation) is Annotated:
            annotation, *extra = get_args(annotation)
            for item in extra:  # a Field(...) in Annotated carries its constraints as metadata
                metadata += list(getattr(item, "metadata", [item]))
        else:
            return annotation, metadata


def unit_of(root: type[BaseModel], key: str) -> str | None:
    """The unit of a numeric key of ``root`` (``platoon.k_v`` -> ``1/s``, ``path.center[0]`` -> ``m``), for axis
    labels and messages; None for a key without one (a count, a factor, a word) or no such key."""
    parts = key.replace("[", ".").replace("]", "").split(".")
    loc = tuple(int(part) if part.isdigit() else part for part in parts if part)
    _, metadata = _field_at(root, loc)
    return next((str(item) for item in metadata if isinstance(item, (Unit, UnitNote))), None)


def _range_text(field: tuple[Any, list[Any]]) -> str:
    """"a finite number >= 0.001 and <= 1000", "an integer >= 1": the declared range of a numeric key."""
    annotation, metadata = field
    bounds = [f"{word} {_number(getattr(item, name))}" for item in metadata for name, word in _BOUND_WORDS
              if isinstance(item, getattr(annotated_types, name.capitalize())) and hasattr(item, name)]
    unit = next((f" {item}" for item in metadata if isinstance(item, Unit)), "")
    note = next((f" ({item})" for item in metadata if isinstance(item, UnitNote)), "")
    bounds = [bound + unit for bound in bounds]
    kind = "an integer" if annotation is int else "a finite number"
    text = " and ".join([f"{kind} {bounds[0]}" if bounds else kind, *bounds[1:]])
    return text + (" (radians: 90 degrees = 1.5708 rad)" if unit == " rad" else note)


def _number(value: float | int) -> str:
    return f"{value:g}" if isinstance(value, float) else str(value)


def _nearest_key(root: type[BaseModel], loc: tuple[Any, ...]) -> str:
    """" (did you mean count?)" for an unknown key ``loc``: the nearest key its table has, if any is near."""
    table, _ = _field_at(root, loc[:-1])
    if not (isinstance(table, type) and issubclass(table, BaseModel)) or not isinstance(loc[-1], str):
        return ""
    table_key = _key_of(loc[:-1])
    return did_you_mean(loc[-1], table.model_fields, f"{table_key}." if table_key else "")


def explain(error: ValidationError, root: type[BaseModel]) -> str:
    """One line for the first problem pydantic found validating ``root``: key, value, expectation."""
    first = error.errors(include_url=False)[0]
    ctx = first.get("ctx") or {}
    loc = tuple(part for part in first["loc"] if not (isinstance(part, str) and part.startswith("function-")))
    key = _key_of(loc)
    if "error" in ctx and isinstance(ctx["error"], (RuleError, Ros2Rule)):  # a rule of a nested table names its own key
        return f"{key}.{ctx['error']}" if key else str(ctx["error"])
    key = key or "a key"  # the key itself is what is wrong (not UTF-8)
    if first["type"] == "extra_forbidden":
        return f"{key}: unknown key{_nearest_key(root, loc)}"
    if first["type"] == "missing":
        return f"{key}: missing (required)"
    if "error" in ctx and isinstance(ctx["error"], Expected):
        return f"{key} = {first['input']!r}: {ctx['error']}"
    if first["type"] in ("string_pattern_mismatch", "string_too_long") and loc == ("name",):
        return (f"name = {first['input']!r}: must be {NAME_RULE} (it names the trace file runs/<name>-<time>.mcap; "
                "without a name key it is the config's file name)")
    if first["type"] == "string_unicode":
        return f"{key} = {first['input']!r}: must be valid UTF-8 text"
    if first["type"] in _RANGE_ERRORS:
        return f"{key} = {first['input']!r}: must be {_range_text(_field_at(root, loc))}"
    message = first["msg"]
    message = message[0].lower() + message[1:] if message else message
    return f"{key} = {first['input']!r}: {message}"
