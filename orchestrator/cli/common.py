"""What every `platoon` command shares: the two consoles, the one-line failure (exit code and message), a
config or a trace loaded with its errors turned into that line, the output checks, the summary table.

No rich markup in what we print: names, paths and config text are the user's ("[[disturbance]]",
"runs/[a]/x.mcap") and must appear as written. The one styled line (``fail``) asks for markup itself.
"""

from __future__ import annotations

from typing import Annotated

import typer

from orchestrator.cli.plain import (check_choice, check_output, claim_trace, console, fail, load_config,  # noqa: F401
                                    output_rule)  # re-exported: the commands import them from here
from orchestrator.support.output import OVERWRITE_HELP  # noqa: F401  (the one output rule, docs/output.md)
from orchestrator.cli.tables import summary_table  # noqa: F401  (re-exported for the commands)
from orchestrator.cli.reporting import load_trace, note_recovery, quiet_nan  # noqa: F401  (re-exported, typer-free)

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
