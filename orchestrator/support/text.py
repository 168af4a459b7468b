"""Numbers as the tables print them (shared by the run's live-link table and the HIL benchmark)."""

from __future__ import annotations

import math
from typing import Any


def ms_text(value: Any) -> str:
    """Seconds as milliseconds with 2 decimals; "-" for a missing value."""
    return f"{value * 1e3:.2f}" if isinstance(value, float) and math.isfinite(value) else "-"
