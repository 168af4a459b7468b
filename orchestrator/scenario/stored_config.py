"""The config a trace was run with, read back for `platoon report`, even when it held inf or NaN.

A trace stores the resolved config as JSON (``platoon.config`` ``resolved``), where inf and NaN become
``null``. Such a config no longer validates, but the trace is still worth reporting (a run with a
non-finite parameter fails, and that failure is what the user wants to look at). So the config is
rebuilt with each null put back as NaN where the model accepts it, else with the key left at its
default and then set to NaN; the keys are returned so the report can say which values it could not
know (every figure that depends on one comes out as nan, never as a made-up number).
"""

from __future__ import annotations

import math
from typing import Any

from pydantic import BaseModel

from orchestrator.scenario.config import Config, ConfigError, config_from_mapping


def null_keys(raw: Any, prefix: str = "") -> list[str]:
    """Dotted keys (``platoon.k_v``, ``path.center``, ``disturbance[0].value``) holding a null."""
    found: list[str] = []
    if isinstance(raw, dict):
        for key, value in raw.items():
            found += null_keys(value, f"{prefix}{key}.")
    elif isinstance(raw, list):
        if any(item is None for item in raw):
            found.append(prefix[:-1])
        for index, item in enumerate(raw):
            if isinstance(item, (dict, list)):
                found += null_keys(item, f"{prefix[:-1]}[{index}].")
    elif raw is None:
        found.append(prefix[:-1])
    return found


def _without_nulls(raw: Any) -> Any:
    """The mapping with every null key (and every list holding a null) removed: defaults take their place."""
    if isinstance(raw, dict):
        return {key: _without_nulls(value) for key, value in raw.items()
                if value is not None and not (isinstance(value, list) and any(item is None for item in value))}
    if isinstance(raw, list):
        return [_without_nulls(item) for item in raw]
    return raw


def _nan_for_nulls(raw: Any) -> Any:
    if isinstance(raw, dict):
        return {key: _nan_for_nulls(value) for key, value in raw.items()}
    if isinstance(raw, list):
        return [_nan_for_nulls(item) for item in raw]
    return math.nan if raw is None else raw


def _set_nan(model: BaseModel, raw: dict[str, Any]) -> BaseModel:
    """``model`` with every field that is null in ``raw`` set to NaN (nested models too; no validation)."""
    update: dict[str, Any] = {}
    for key, value in raw.items():
        current = getattr(model, key, None)
        if value is None:
            update[key] = math.nan
        elif isinstance(value, list) and any(item is None for item in value):
            update[key] = [math.nan if item is None else item for item in value]
        elif isinstance(value, dict) and isinstance(current, BaseModel):
            update[key] = _set_nan(current, value)
    return model.model_copy(update=update) if update else model


def stored_config(raw: dict[str, Any]) -> tuple[Config, list[str]]:
    """The config of a trace and the keys that were not finite (stored as null). Raises ConfigError."""
    nulls = null_keys(raw)
    if not nulls:
        return config_from_mapping(raw), []
    try:
        return config_from_mapping(_nan_for_nulls(raw)), nulls
    except ConfigError:
        pass
    config = config_from_mapping(_without_nulls(raw))
    return _set_nan(config, raw), nulls  # type: ignore[return-value]
