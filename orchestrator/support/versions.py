"""The versions a trace records and `platoon --version` prints: the package, its FMUs, FMPy, pythonfmu, Python."""

from __future__ import annotations

import importlib.metadata
import platform

import fmus
from orchestrator import __version__


def tool_versions() -> dict[str, str]:
    return {
        "platoon-cosim": __version__,
        "fmus": fmus.__version__,
        # from the installed metadata: importing pythonfmu only for its version costs ~80 ms of start-up
        "fmpy": importlib.metadata.version("fmpy"),
        "pythonfmu": importlib.metadata.version("pythonfmu"),
        "python": platform.python_version(),
    }


def version_line() -> str:
    """What `platoon --version` prints: ``platoon 0.1.0 (fmus 0.1.0, fmpy ..., python 3.11.7)``."""
    versions = tool_versions()
    return f"platoon {versions.pop('platoon-cosim')} (" + ", ".join(f"{name} {version}" for name, version in versions.items()) + ")"
