"""`platoon --help`, `platoon COMMAND --help` and a bare `platoon`: typer's own page, shown again from a
cache without importing typer.

Rendering a help page imports typer, click, rich and typer's rich help module (with markdown-it,
pygments and attrs): about 0.2 s of a 0.25 s `platoon --help`, for a page that only changes when the
command line, the code or the terminal does (docs/performance.md, "Start-up"). So the first time a
page is shown, its bytes (both streams, as typer wrote them) and its exit code are stored under the
user's cache folder; the next time, if nothing it depends on changed, those bytes are written again.

What a page depends on, all in its key or checked before it is used:
- the command line, the interpreter (its path and version) and the streams' encodings;
- the terminal: for stdin, stdout and stderr, whether each is a terminal and its size;
- the environment variables rich, click and typer read (colour, width, completion, typer's own);
- every module that was loaded when the page was rendered, outside the standard library: its file's
  size and modification time (an edit in a checkout, or an upgrade of typer or rich, makes a new page).
Anything else (another command, an option, a cache that cannot be read or written) goes to typer as
before. Standard library only, and little of it: this runs before every `platoon` command.
"""

from __future__ import annotations

import json
import os
import re
import sys
from pathlib import Path
from typing import Any, Callable, NoReturn

from orchestrator.support.cache_files import cache_folder, loaded_files, stamps, write_whole

_WORD = re.compile(r"[a-z][a-z0-9-]*")  # a command's name (a help request names commands, then --help)
_ENVIRONMENT = ("NO_COLOR", "FORCE_COLOR", "PY_COLORS", "TERM", "COLORTERM", "COLUMNS", "LINES", "TERMINAL_WIDTH",
                "TTY_COMPATIBLE", "TTY_INTERACTIVE", "JUPYTER_COLUMNS", "JUPYTER_LINES", "GITHUB_ACTIONS",
                "DATABRICKS_RUNTIME_VERSION", "UNICODE_VERSION", "PYTHONIOENCODING", "PYTHONUTF8", "LANG", "LC_ALL",
                "LC_CTYPE", "TYPER_USE_RICH")
_PREFIXES = ("_TYPER", "TYPER_", "COMP_")  # typer's switches, shell completion


def is_help_request(args: list[str]) -> bool:
    """A bare `platoon` (typer shows the help), or command names followed by ``--help``."""
    return not args or (args[-1] == "--help" and all(_WORD.fullmatch(word) for word in args[:-1]))


def replay(args: list[str]) -> None:
    """Write the stored page of ``args`` and exit with its code, if one is stored and still valid;
    return otherwise (typer then renders it)."""
    try:
        stored = json.loads(_entry(args).read_text(encoding="utf-8"))
        if stored["modules"] != stamps(stored["modules"]):
            return
    except (OSError, ValueError, KeyError, TypeError):
        return
    _write(sys.stdout, stored["stdout"])
    _write(sys.stderr, stored["stderr"])
    os._exit(stored["code"])


def recording(command: Callable[[], object], args: list[str]) -> Callable[[], NoReturn]:
    """``command`` (the typer app) with what it writes on both streams stored as ``args``'s page."""

    def record() -> NoReturn:
        streams = sys.stdout, sys.stderr
        copies = sys.stdout, sys.stderr = _Copy(sys.stdout), _Copy(sys.stderr)
        try:
            command()
            code: object = 0
        except SystemExit as done:  # typer's way to end, with or without an error
            code = done.code or 0
        finally:
            sys.stdout, sys.stderr = streams
        if isinstance(code, int):
            _store(args, code, *(copy.written for copy in copies))
        raise SystemExit(code)

    return record


class _Copy:
    """A text stream that keeps a copy of what is written through it (rich and click see the stream's own
    isatty, fileno and encoding)."""

    def __init__(self, stream: Any) -> None:
        self._stream = stream
        self._parts: list[str] = []

    def write(self, text: str) -> int:
        written = self._stream.write(text)  # first: click tries ``write(b"")`` to learn what the stream takes
        self._parts.append(text)
        return written

    @property
    def written(self) -> str:
        return "".join(self._parts)

    def __getattr__(self, name: str) -> Any:
        return getattr(self._stream, name)


def _write(stream: Any, text: str) -> None:
    if text:
        stream.write(text)
        stream.flush()


def _store(args: list[str], code: int, stdout: str, stderr: str) -> None:
    write_whole(_entry(args), json.dumps({"code": code, "stdout": stdout, "stderr": stderr,
                                          "modules": stamps(loaded_files())}))


def _terminal(descriptor: int) -> list[Any]:
    try:
        size = list(os.get_terminal_size(descriptor))
    except OSError:
        size = None
    return [os.isatty(descriptor), size]


def _entry(args: list[str]) -> Path:
    """The page's file in the cache folder: named by a hash of its key."""
    environment = {name: value for name, value in os.environ.items()
                   if name in _ENVIRONMENT or name.startswith(_PREFIXES) or name.endswith("_COMPLETE")}
    key = json.dumps([args, sys.executable, sys.version, [getattr(stream, "encoding", None) for stream in
                                                          (sys.stdout, sys.stderr)],
                      [_terminal(descriptor) for descriptor in (0, 1, 2)], sorted(environment.items())])
    import hashlib  # here: OpenSSL's loading is ~2 % of the commands that show no help

    return cache_folder("help") / f"{hashlib.sha256(key.encode()).hexdigest()[:32]}.json"
