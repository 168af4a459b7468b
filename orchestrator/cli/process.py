"""How a `platoon` process ends: the command's exit code, then out without interpreter teardown."""

from __future__ import annotations

import errno
import os
import sys
from typing import Callable, NoReturn


def run_and_exit(command: Callable[[], object], without_typer: bool = False) -> NoReturn:
    """Run ``command``, then leave with its exit code and without interpreter teardown.

    pythonfmu FMUs embed themselves in the host's interpreter, and its teardown after they ran
    intermittently corrupts the heap (glibc aborts with "corrupted double-linked list", seen in
    roughly one run in five when started through the console script). Every file is closed and every
    line printed by the time a command returns, so we flush and exit with the command's code directly.

    ``without_typer``: the command runs without typer (orchestrator/cli/launch.py), so this does what
    typer does around a command: Ctrl-C that the command did not handle exits 130, a closed stdout or
    stderr (EPIPE) exits 1, both without a traceback.
    """
    code = 0
    try:
        command()
    except SystemExit as done:
        code = done.code if isinstance(done.code, int) else (0 if done.code is None else 1)
        if isinstance(done.code, str):
            print(done.code, file=sys.stderr)
    except BaseException as error:  # an unexpected error: show it, as Python would, then exit 1
        code = _unexpected(error, without_typer)
    finally:
        try:
            sys.stdout.flush()
            sys.stderr.flush()
        except OSError:
            if not without_typer:  # typer made a closed pipe's streams quiet; without it, so do we
                raise
    os._exit(code)


def _unexpected(error: BaseException, without_typer: bool) -> int:
    """The exit code of a command that raised ``error``; a traceback unless typer would have shown none."""
    if without_typer and isinstance(error, KeyboardInterrupt):
        return 130
    if without_typer and isinstance(error, OSError) and error.errno == errno.EPIPE:
        return 1
    import traceback

    traceback.print_exc()
    return 1
