""""did you mean ...?" for a mistyped name (a config key, an option's value), as click does for commands.

difflib from the standard library: its ratio finds ``cout`` -> ``count`` and ``fmi`` -> ``fmus`` without
a dependency; a cut-off of 0.6 (difflib's default) suggests nothing for a name unlike every choice.
"""

from __future__ import annotations

from typing import Iterable


def did_you_mean(name: str, choices: Iterable[str], prefix: str = "") -> str:
    """``" (did you mean platoon.count?)"`` for the choice nearest ``name`` (shown after ``prefix``, e.g. the
    table a key is in: names are compared without it), or "" when none is near."""
    import difflib  # imported with a mistake to name: every run and report imports this module, few need it

    near = difflib.get_close_matches(name, list(choices), n=1)
    return f" (did you mean {prefix}{near[0]}?)" if near else ""
