"""What every `platoon` command shares: the two consoles, the one-line failure (exit code and message), a
config or a trace loaded with its errors turned into that line, the output checks, the summary table.

No rich markup in what we print: names, paths and config text are the user's ("[[disturbance]]",
"runs/[a]/x.mcap") and must appear as written. The one styled line (``fail``) asks for markup itself.
"""

from __future__ import annotations

import json
import warnings
from contextlib import contextmanager
from pathlib import Path
from typing import Annotated, Iterator

import typer

from orchestrator.cli.plain import (check_choice, check_output, claim_trace, console, fail, load_config,  # noqa: F401
                                    output_rule)  # re-exported: the commands import them from here
from orchestrator.support.output import OVERWRITE_HELP  # noqa: F401  (the one output rule, docs/output.md)
from orchestrator.cli.tables import summary_table  # noqa: F401  (re-exported for the commands)

# The consoles (orchestrator/cli/plain.py makes them: markup off, the text is the user's)
out = console()


err = console(stderr=True)


# Metavars that show what an option takes (typer would print <str> or <list[str]>)
SET_METAVAR = "KEY=VALUE"


def choices_metavar(choices: tuple[str, ...]) -> str:
    """``<a|b|c>``: the allowed values of an option, as typer shows a choice type, for an option we check
    ourselves (so a wrong value is our one-line error, not typer's framed box)."""
    return "<" + "|".join(choices) + ">"


AllowLong = Annotated[bool, typer.Option("--allow-long", help="run even above the size limits (docs/config.md: more than "
                                         "1e6 steps, 1000 substeps per step or 1e8 FMU-substeps)")]


Overwrite = Annotated[bool, typer.Option("--overwrite", help=OVERWRITE_HELP)]


@contextmanager
def quiet_nan(quiet: bool) -> Iterator[None]:
    """Silence numpy's invalid-value warnings when a config's non-finite values make figures nan on purpose."""
    if not quiet:
        yield
        return
    import numpy as np

    with np.errstate(all="ignore"), warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        yield


def note_recovery(loaded, note) -> None:
    """A trace written by `platoon trace recover` with damaged stretches skipped: say which time is missing."""
    record = loaded.metadata.get("platoon.recovery")
    if not record or record.get("damaged", "0") == "0":
        return
    from orchestrator.trace.recovery import describe_lost

    lost = [tuple(pair) for pair in json.loads(record.get("lost", "[]"))]
    note(f"warning: recovered from a damaged trace; data is missing between {describe_lost(lost)}",
         highlight=False, soft_wrap=True)


def load_trace(trace: Path, **selection):
    """The trace read back (``selection``: ``load``'s components, start, end, errors), with a progress bar
    or lines on stderr when reading takes more than a second; exit 2 with one line when it cannot be read."""
    from orchestrator.observers.progress import late_progress
    from orchestrator.trace import TraceError, load

    if not trace.is_file():
        fail(2, f"trace {trace}: no such file")
    try:
        with late_progress(f"reading {trace.name}", err, "chunks") as shown:
            return load(trace, progress=shown, **selection)
    except TraceError as error:  # says what is wrong and what to do (e.g. `platoon trace recover`)
        fail(2, f"trace {trace}: not a readable MCAP trace: {error}")
    except Exception as error:  # any other reader failure means the file is not a usable trace
        fail(2, f"trace {trace}: not a readable MCAP trace ({error}); try `platoon trace recover {trace}`")


