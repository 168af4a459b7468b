"""The building blocks of the config's schema (orchestrator/scenario/config.py): the strict base model, every
number's declared range and unit (``Positive``, ``Angle``, ...), which pydantic enforces and the error text
quotes back (config_errors.py), free text and run names, and the error a cross-field rule raises."""

from __future__ import annotations

import math
from typing import Annotated, Any

from pydantic import AfterValidator, BaseModel, ConfigDict, Field

from .config_logic import PULSE_UNITS  # a disturbance's value, by its kind

class StrictModel(BaseModel):
    # defer_build: each model's validator is built when first used, not at import; a run validates one Config,
    # whose validator holds every table, so the tables' own were built for nothing (~0.03 s of a run's start-up)
    model_config = ConfigDict(extra="forbid", strict=True, frozen=True, allow_inf_nan=False, defer_build=True)


class Expected(ValueError):
    """A field validator's complaint: what the value must be (``_explain`` adds the key and the value)."""


# Ranges. A platoon lives on a ground plane: 1000 km is far beyond any scenario and keeps doubles at
# sub-micrometre resolution (ulp(1e6) = 1.2e-10 m), so lengths and coordinates stay within it.
LENGTH_MAX = 1e6  # m
# The smallest length, speed, gain or time constant: a millimetre, a millimetre per second, a speed
# loop of 1000 s. Below, nothing physical is left and the analysis and the models divide by ~0.
SMALL = 1e-3
SPEED_MAX = 1000.0  # m/s: three times the speed of sound, far above any vehicle
GAIN_MAX = 1000.0  # 1/s: a speed loop faster than 1 ms is not a vehicle (and needs substeps below 1 ms)
ANGLE_MAX = 2.0 * math.pi  # rad: one turn either way states every direction
PULSE_MAX = 1e6  # m/s² or m/s (PULSE_UNITS): a disturbance beyond this only produces overflow



class Unit(str):
    """The unit of a numeric key, printed with its range in an error ("<= 6.28319 rad"): configs use SI
    units and radians, and a message says which."""


class UnitNote(str):
    """The unit of a numeric key that depends on another key, said once after its range in an error."""


# Every float is finite (allow_inf_nan=False above); these add the range and the unit.
Positive = Annotated[float, Field(gt=0.0)]
Duration = Annotated[float, Field(gt=0.0), Unit("s")]
Length = Annotated[float, Field(ge=-LENGTH_MAX, le=LENGTH_MAX), Unit("m")]
PositiveLength = Annotated[float, Field(ge=SMALL, le=LENGTH_MAX), Unit("m")]
Speed = Annotated[float, Field(ge=SMALL, le=SPEED_MAX), Unit("m/s")]
Gain = Annotated[float, Field(ge=SMALL, le=GAIN_MAX), Unit("1/s")]
Angle = Annotated[float, Field(ge=-ANGLE_MAX, le=ANGLE_MAX), Unit("rad")]
Pulse = Annotated[float, Field(ge=-PULSE_MAX, le=PULSE_MAX),
                  UnitNote(", ".join(f'{unit} for kind = "{kind}"' for kind, unit in PULSE_UNITS.items()))]

# The run's name becomes a file name (runs/<name>-<time>.mcap): letters, digits (any script), and a
# few punctuation marks, starting with a letter or digit, so it can hold no path separator, no "..",
# no control character and no shell-unfriendly leading "-".
# The length is a separate constraint: "[...]{0,99}" in the pattern made pydantic-core's regex engine
# build 99 copies of the Unicode class \w, ~30 ms of every run's start-up (docs/performance.md).
NAME_PATTERN = r"^\w[\w .,+=@#()-]*$"
NAME_LENGTH_MAX = 100
NAME_RULE = "letters, digits, spaces and . , + = @ # ( ) - _, starting with a letter or digit, at most 100 characters"


def _clean_text(text: str) -> str:
    """Free text may span lines and hold tabs, but no NUL or other control character (they break file
    names, Zenoh endpoints, terminals and C strings further on), and must be encodable as UTF-8 (a
    command-line argument that was not UTF-8 arrives with lone surrogates, which no file can hold)."""
    try:
        text.encode("utf-8")
    except UnicodeEncodeError:
        raise Expected("must be valid UTF-8 text") from None
    bad = [c for c in text if (ord(c) < 0x20 and c not in "\t\n\r") or ord(c) == 0x7F]
    if bad:
        raise Expected(f"must be text without control characters (found {bad[0]!r})")
    return text


Text = Annotated[str, AfterValidator(_clean_text)]
Name = Annotated[str, Field(pattern=NAME_PATTERN, max_length=NAME_LENGTH_MAX)]

# RK4 alone is stable on dx/dt = -x/T for substeps h < 2.785 T (its real stability interval); coupled
# to the guidance through the speed chain it needs a margin: the paper's platoon at k_v = 1000 1/s
# diverged at h = 2.5 T and ran at h = 2 T (measured, docs/config.md).
RK4_STABILITY = 2.0

# Steps and substeps are counted in integers from float ratios: exact only up to 2**53.
COUNT_LIMIT = 2**53



class RuleError(ValueError):
    def __init__(self, key: str, value: Any, expected: str, message: str | None = None) -> None:
        super().__init__(message or f"{key} = {value!r}: expected {expected}")
        self.key, self.value, self.expected = key, value, expected


def rule(key: str, value: Any, expected: str) -> RuleError:
    return RuleError(key, value, expected)
