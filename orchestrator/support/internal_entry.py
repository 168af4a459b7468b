"""Processes the tool starts itself (``python -m orchestrator.sweep.worker``, ``...trace.serve``,
``...bench.child``): what they say to a person who runs one by hand.

They take pipes, file descriptors or JSON meant for a program, so a curious ``--help`` or a wrong
argument list must not end in a traceback: ``--help`` prints the usage and the module's docstring (who
starts it and why; exit 0), anything else that does not fit is one ``error:`` line (exit 2). Standard
library only: these processes keep their start-up small.
"""

from __future__ import annotations

import sys
from typing import Callable


def check_arguments(argv: list[str], usage: str, doc: str | None, count: int | None = None,
                    fits: Callable[[list[str]], bool] | None = None) -> None:
    """Leave at once on ``-h``/``--help`` (usage and ``doc``), or on arguments that do not fit: another
    number than ``count`` (when given), or ``fits(argv)`` false; return otherwise."""
    if argv[:1] in (["-h"], ["--help"]):
        sys.stdout.write(f"usage: {usage}\n\n{(doc or '').strip()}\n")
        raise SystemExit(0)
    if count is not None and len(argv) != count or fits is not None and not fits(argv):
        sys.stderr.write(f"error: usage: {usage} (started by platoon itself; --help says by what)\n")
        raise SystemExit(2)
