"""What users look at: ``platoon layout`` (a Foxglove layout fitted to one run) and ``platoon figure``
(the paper's figure pair from two traces). The layout itself is made in orchestrator/trace/layout.py.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import TYPE_CHECKING, Annotated, Optional

import typer

from orchestrator.cli.common import Overwrite

if TYPE_CHECKING:
    pass

from orchestrator.trace.layout import layout_path, read_run_view, recorded_config, run_layout

FIGURE_SUFFIXES = (".pdf", ".svg", ".png")


def layout_command(
    trace: Annotated[Path, typer.Argument(metavar="TRACE.mcap", help="trace written by `platoon run`")],
    out: Annotated[Optional[Path], typer.Option("--out", help="layout file (default: beside the trace, <stem>.layout.json)")] = None,
    overwrite: Overwrite = False,
) -> None:
    """Write a Foxglove/Lichtblick layout fitted to a trace: its path in view, one plot series per vehicle."""
    from orchestrator.cli.common import fail, out as console, output_rule
    from orchestrator.support.output import check_target, write_text
    from orchestrator.trace.layout import LAYOUT

    path = out or layout_path(trace)
    with output_rule():  # before the trace is read: a refused --out costs nothing
        check_target(path, overwrite, [trace], kind=LAYOUT)
    try:
        view = read_run_view(trace)
    except ValueError as error:
        fail(2, f"trace {trace}: {error}")
    if not view.vehicles:
        fail(2, f"trace {trace}: records no vehicle")
    with output_rule():
        write_text(path, json.dumps(run_layout(view.config, len(view.vehicles)), indent=2) + "\n")
    console.print(f"wrote {path}", highlight=False, soft_wrap=True)


def figure_command(
    first: Annotated[Path, typer.Argument(metavar="A.mcap", help="trace of the left column (the paper: regular law)")],
    second: Annotated[Path, typer.Argument(metavar="B.mcap", help="trace of the right column (the paper: sine law)")],
    out: Annotated[Path, typer.Option("--out", help="figure file: .pdf, .svg (vector) or .png")],
    dpi: Annotated[int, typer.Option(min=30, max=1200, help="dots per inch of a PNG (the figure is 12.4 x 15 in)")] = 150,
    overwrite: Overwrite = False,
) -> None:
    """Draw the paper's figure pair from two traces: speed, gap and path errors, and X-Y, side by side."""
    from orchestrator.cli.common import err, fail, load_trace, out as console, output_rule
    from orchestrator.support.output import IMAGE, check_target

    if out.suffix.lower() not in FIGURE_SUFFIXES:
        fail(2, f"--out {out}: expected a file ending in {', '.join(FIGURE_SUFFIXES)}")
    with output_rule():
        check_target(out, overwrite, [first, second], kind=IMAGE)

    runs = []
    for trace in (first, second):
        loaded = load_trace(trace)
        if loaded.config is None:
            fail(2, f"trace {trace}: has no platoon.config metadata (not written by platoon run?)")
        if not loaded.vehicles() or any(len(loaded.component(v)["t"]) == 0 for v in loaded.vehicles()):
            fail(2, f"trace {trace}: no recorded communication point, nothing to draw "
                     f"(run {loaded.run.get('status', '?')})")
        try:
            runs.append((loaded, recorded_config(loaded.config)))
        except ValueError as error:
            fail(2, f"trace {trace}: {error}")
    # said once both traces are read (a bad input is its one line), before the plotting library and the drawing:
    # tens of seconds on a loaded machine
    err.print(f"figure: drawing {out} from {first} and {second} ...", highlight=False, soft_wrap=True)
    from orchestrator.analysis.figure import draw_pair, save

    figure = draw_pair(runs)
    with output_rule():
        save(figure, out, dpi)
    console.print(f"wrote {out}", highlight=False, soft_wrap=True)


def register(app: typer.Typer) -> None:
    """Add ``layout`` and ``figure`` to ``platoon``."""
    app.command("layout")(layout_command)
    app.command("figure")(figure_command)
