"""`platoon --help` shown again from the cache (orchestrator/cli/help_cache.py): the same bytes and exit code
as typer's own rendering, without importing typer; rendered afresh when anything it depends on changed.

Each case runs the console script's code in fresh interpreters (``python -X importtime -m orchestrator``,
whose import report on stderr says whether typer was loaded), with a cache folder of its own.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]


def platoon(cache: Path, *args: str, width: int = 100) -> tuple[int, str, str, bool]:
    """Exit code, stdout, stderr (import lines removed) of `platoon ARGS`, and whether typer was imported."""
    env = {**os.environ, "XDG_CACHE_HOME": str(cache), "PYTHONPATH": str(REPO), "COLUMNS": str(width),
           "NO_COLOR": "1", "TERM": "dumb"}
    done = subprocess.run([sys.executable, "-X", "importtime", "-P", "-m", "orchestrator", *args], env=env,
                          capture_output=True, text=True, timeout=120)
    lines = done.stderr.splitlines(keepends=True)
    imports = [line for line in lines if line.startswith("import time:")]
    stderr = "".join(line for line in lines if not line.startswith("import time:"))
    return done.returncode, done.stdout, stderr, any(line.rstrip().endswith(" typer") for line in imports)


@pytest.mark.parametrize("args", [["--help"], [], ["sweep", "--help"], ["trace", "recover", "--help"],
                                  ["no-such-command", "--help"]])
def test_a_help_page_is_shown_again_as_typer_rendered_it_without_typer(tmp_path: Path, args: list[str]) -> None:
    first = platoon(tmp_path, *args)
    again = platoon(tmp_path, *args)
    assert first[3] and not again[3]  # rendered by typer once, then from the cache
    assert again[:3] == first[:3]
    assert first[0] != 0 or " Usage: " in first[1]
    assert (first[0] == 2 and "No such command" in first[2]) if args[:1] == ["no-such-command"] else first[2] == ""


def test_another_width_is_another_page(tmp_path: Path) -> None:
    wide, narrow = platoon(tmp_path, "--help", width=120), platoon(tmp_path, "--help", width=60)
    assert narrow[3] and narrow[1] != wide[1]
    assert max(map(len, narrow[1].splitlines())) <= 60 < max(map(len, wide[1].splitlines()))


def test_a_changed_module_renders_the_page_again(tmp_path: Path) -> None:
    first = platoon(tmp_path, "--help")
    (entry,) = (tmp_path / "platoon-cosim" / "help").glob("*.json")
    stored = json.loads(entry.read_text())
    app = next(name for name in stored["modules"] if name.endswith(os.path.join("orchestrator", "cli", "app.py")))
    stored["modules"][app][1] -= 1  # as if app.py had been edited since: another modification time
    entry.write_text(json.dumps(stored))
    again = platoon(tmp_path, "--help")
    assert again[3] and again[:3] == first[:3]
    assert not platoon(tmp_path, "--help")[3]  # and stored again


def test_a_cache_folder_that_cannot_be_written_leaves_help_as_it_was(tmp_path: Path) -> None:
    blocked = tmp_path / "file"
    blocked.write_text("not a folder")
    first, again = platoon(blocked, "--help"), platoon(blocked, "--help")
    assert first[3] and again[3] and first[:3] == again[:3] and first[0] == 0
