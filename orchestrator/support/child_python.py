"""Start one of this package's modules in a child interpreter: ``python -P -m MODULE``, with the folder
this package was imported from first on PYTHONPATH.

``python -m`` puts the current folder first on ``sys.path``, so a child started that way imports
whatever ``orchestrator`` the current folder holds: run from another checkout, or from a folder with an
older copy, the child would run other code than its parent (it did: a benchmark that ran an older
build from the repository got the repository's trace worker, which refused its arguments). ``-P``
(Python 3.11) leaves the current folder out, and PYTHONPATH names this package's own folder, so an
install, an editable checkout and a checkout on PYTHONPATH all give the child the parent's code.
"""

from __future__ import annotations

import os
import sys
from pathlib import Path

_ROOT = str(Path(__file__).resolve().parents[2])  # the folder holding the orchestrator package


def module_command(module: str, *arguments: str) -> list[str]:
    """The command line that runs ``module`` (e.g. ``orchestrator.trace.serve``) in a child interpreter."""
    return [sys.executable, "-P", "-m", module, *arguments]


def module_environment() -> dict[str, str]:
    """This process's environment, with this package's folder first on PYTHONPATH."""
    paths = [_ROOT, *filter(None, os.environ.get("PYTHONPATH", "").split(os.pathsep))]
    return {**os.environ, "PYTHONPATH": os.pathsep.join(dict.fromkeys(paths))}
