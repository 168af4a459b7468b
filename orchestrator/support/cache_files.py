"""Files a `platoon` command keeps under the user's cache folder to skip work it did before (help pages,
validated configs), and how such a file says it is still good: the code it was made by, file by file.

Standard library only, and little of it: this runs before every `platoon` command.
"""

from __future__ import annotations

import os
import sys
from pathlib import Path
from typing import Any

_STDLIB = os.path.dirname(os.__file__)


def cache_folder(kind: str) -> Path:
    """``$XDG_CACHE_HOME/platoon-cosim/<kind>`` (``~/.cache`` without the variable)."""
    home = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    return Path(home) / "platoon-cosim" / kind


def loaded_files() -> list[str]:
    """The file of every module loaded now, outside the standard library: the code a result depends on."""
    return sorted({file for module in list(sys.modules.values())
                   if isinstance(file := getattr(module, "__file__", None), str) and not file.startswith(_STDLIB)})


def stamps(files: Any) -> dict[str, list[int] | None]:
    """Each file's size and modification time (None: gone): equal stamps, the same code."""
    found: dict[str, list[int] | None] = {}
    for file in files:
        try:
            status = os.stat(file)
            found[file] = [status.st_size, status.st_mtime_ns]
        except OSError:
            found[file] = None
    return found


def modified(path: str | Path) -> int | None:
    """A file's or folder's modification time (ns), None when it cannot be read: a folder's changes when an
    entry is added to or removed from it."""
    try:
        return os.stat(path).st_mtime_ns
    except OSError:
        return None


def write_whole(path: Path, text: str) -> None:
    """Write ``text`` to ``path`` whole or not at all (two processes at once each write their own, then rename);
    a folder that cannot be written is no error: the work is done again next time, as without a cache."""
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        partial = path.with_name(f"{path.name}.{os.getpid()}.part")
        partial.write_text(text, encoding="utf-8")
        os.replace(partial, path)
    except OSError:
        pass
