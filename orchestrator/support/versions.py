"""The versions a trace records and `platoon --version` prints: the package, its FMUs, FMPy, pythonfmu, Python."""

from __future__ import annotations

import json
import platform
import sys
import zlib

import fmus
from orchestrator import __version__
from orchestrator.support.cache_files import cache_folder, modified, write_whole

INSTALLED = ("fmpy", "pythonfmu")  # read from their installed metadata: importing them only for a version costs ~80 ms


def tool_versions() -> dict[str, str]:
    installed = installed_versions(INSTALLED)
    return {
        "platoon-cosim": __version__,
        "fmus": fmus.__version__,
        "fmpy": installed["fmpy"],
        "pythonfmu": installed["pythonfmu"],
        "python": platform.python_version(),
    }


def installed_versions(names: tuple[str, ...]) -> dict[str, str]:
    """``importlib.metadata.version`` of each of ``names``, kept under ``~/.cache/platoon-cosim/versions/``.

    Every run records these in its trace, and importing importlib.metadata (email and its parsers) and
    searching ``sys.path`` was ~85 M instructions, an eighth of a 10-step run (docs/performance.md,
    "Start-up"). What the search finds depends only on ``sys.path`` and on which distributions its folders
    hold: installing, upgrading or removing one adds or removes a metadata folder, which changes the
    modification time of the folder holding it. So the answer is kept with ``sys.path`` and the modification
    time of each of its folders, and asked again as soon as any differs."""
    key = {"names": list(names), "path": [[entry, modified(entry or ".")] for entry in sys.path]}
    entry = cache_folder("versions") / f"installed-{zlib.crc32(json.dumps(sys.path).encode()):08x}.json"  # one a sys.path
    try:
        known = json.loads(entry.read_text(encoding="utf-8"))
        if isinstance(known, dict) and known.get("key") == key and isinstance(known.get("versions"), dict):
            return known["versions"]
    except (OSError, ValueError):
        pass
    import importlib.metadata

    versions = {name: importlib.metadata.version(name) for name in names}
    write_whole(entry, json.dumps({"key": key, "versions": versions}))
    return versions


def version_line() -> str:
    """What `platoon --version` prints: ``platoon 0.1.0 (fmus 0.1.0, fmpy ..., python 3.11.7)``."""
    versions = tool_versions()
    return f"platoon {versions.pop('platoon-cosim')} (" + ", ".join(f"{name} {version}" for name, version in versions.items()) + ")"
