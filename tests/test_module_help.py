"""``python -m MODULE --help`` of every runnable module under orchestrator/, bridge/, fmus/ and benchmarks/: a usage
text and exit 0, never a traceback, even for the processes the tool starts itself (real subprocesses).

Runnable: a package with a ``__main__.py``, or a module with an ``if __name__ == "__main__"`` block.
"""

from __future__ import annotations

import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
MAIN_BLOCK = re.compile(r'^if __name__ == "__main__"', re.MULTILINE)


def runnable_modules() -> list[str]:
    found = []
    for package in ("orchestrator", "bridge", "fmus", "benchmarks"):
        for path in sorted((REPO / package).rglob("*.py")):
            parts = path.relative_to(REPO).with_suffix("").parts
            if path.name == "__main__.py":
                found.append(".".join(parts[:-1]))
            elif MAIN_BLOCK.search(path.read_text()):
                found.append(".".join(parts))
    return found


def test_the_walk_finds_the_runnable_modules() -> None:
    modules = runnable_modules()
    for expected in ("orchestrator", "orchestrator.cli", "orchestrator.sweep.worker", "orchestrator.trace.serve",
                     "benchmarks.child", "benchmarks.trace_memory"):
        assert expected in modules


@pytest.mark.parametrize("module", runnable_modules())
def test_help_of_a_runnable_module_never_tracebacks(module: str) -> None:
    env = {**os.environ, "PYTHONPATH": str(REPO), "COLUMNS": "100", "NO_COLOR": "1", "TERM": "dumb"}
    result = subprocess.run([sys.executable, "-m", module, "--help"], cwd=REPO, env=env, stdin=subprocess.DEVNULL,
                            capture_output=True, text=True, timeout=120)
    assert "Traceback" not in result.stdout + result.stderr, result.stderr
    assert result.returncode == 0, result.stderr
    assert "usage" in result.stdout.lower(), result.stdout  # says how it is run
