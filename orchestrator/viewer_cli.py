"""What users look at: ``platoon layout`` (a Foxglove layout fitted to one run) and ``platoon figure``
(the paper's figure pair from two traces). Kept apart from cli.py so that the viewing commands sit
together; ``platoon run`` calls ``write_run_layout`` once, after the run.

A static layout cannot fit both the paper's 50 m circle and the m3pi's 1 m one (the 3D panel's camera
is fixed by the layout), so each run gets its own: ``runs/x.mcap`` gets ``runs/x.layout.json`` (the
trace's stem: the pair sorts together, and the viewer's file dialog, which filters on ``.json``, shows it).
"""

from __future__ import annotations

import json
from contextlib import suppress
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Annotated, Any, Optional

import typer

if TYPE_CHECKING:
    from .config import Config

FIGURE_SUFFIXES = (".pdf", ".svg", ".png")


@dataclass(frozen=True)
class RunView:
    """What a layout needs from a trace: its config and the vehicles it recorded."""

    config: "Config"
    vehicles: list[str]


def layout_path(trace: Path) -> Path:
    """The layout written beside a trace: ``runs/x.mcap`` -> ``runs/x.layout.json``."""
    return trace.with_name(trace.stem + ".layout.json")


def run_layout(config: "Config", vehicles: int) -> dict[str, Any]:
    from .trace.foxglove import SceneSettings, layout

    return layout(vehicles, SceneSettings.of(config))


def write_run_layout(trace: Path, config: "Config", warn: bool = True) -> Path | None:
    """Write the layout fitted to ``config``'s run beside ``trace``; returns its path.

    A layout that cannot be written (disk full, a folder in its place) costs the user nothing of the
    run: None, and the run's summary and exit status stand; ``warn`` says so in one line on stderr (a
    run that failed or was stopped says only that, in its one error line).
    """
    path = layout_path(trace)
    try:
        path.write_text(json.dumps(run_layout(config, config.platoon.count), indent=2) + "\n")
    except OSError as error:
        with suppress(OSError):  # no half-written layout (a folder in its place stays)
            if path.is_file():
                path.unlink()
        if not warn:
            return None
        from .cli import err

        err.print(f"warning: layout {path} not written: {error.strerror or error}", highlight=False, markup=False, soft_wrap=True)
        return None
    return path


def recorded_config(raw: Any) -> "Config":
    """The config a trace recorded; ValueError (one line) if it is invalid or held inf/NaN (no view fits those)."""
    from .config import ConfigError
    from .stored_config import stored_config

    try:
        config, non_finite = stored_config(raw)
    except ConfigError as error:
        raise ValueError(f"its recorded config is not valid: {error}") from None
    if non_finite:
        raise ValueError(f"its recorded config held values that were not finite ({', '.join(non_finite)})")
    return config


def read_run_view(trace: Path) -> RunView:
    """The config and vehicle names of a trace from its summary and metadata (no message is read).

    Raises ValueError with a one-line reason when the file is not a trace written by ``platoon run``.
    """
    from mcap.reader import make_reader

    from .trace.format import CHANNEL_PREFIX, MAGIC, vehicle_names

    if not trace.is_file():
        raise ValueError("no such file")
    with open(trace, "rb") as stream:
        if stream.read(len(MAGIC)) != MAGIC:
            raise ValueError("not an MCAP file (no MCAP magic at its start)")
    try:
        with open(trace, "rb") as stream:
            reader = make_reader(stream)
            summary = reader.get_summary()
            metadata = {item.name: dict(item.metadata) for item in reader.iter_metadata()}
    except Exception as error:  # any reader failure: not a usable trace
        raise ValueError(f"not a readable MCAP trace ({error})") from None
    if summary is None:
        raise ValueError("not a finished MCAP trace (no summary); try `platoon trace recover`")
    record = metadata.get("platoon.config", {})
    if "resolved" not in record:
        raise ValueError("has no platoon.config metadata (not written by platoon run?)")
    try:
        raw = json.loads(record["resolved"])
    except json.JSONDecodeError as error:
        raise ValueError(f"its recorded config is not JSON: {error}") from None
    config = recorded_config(raw)
    topics = [channel.topic[len(CHANNEL_PREFIX):] for channel in summary.channels.values()
              if channel.topic.startswith(CHANNEL_PREFIX)]
    return RunView(config, vehicle_names(topics))


def layout_command(
    trace: Annotated[Path, typer.Argument(metavar="TRACE.mcap", help="trace written by `platoon run`")],
    out: Annotated[Optional[Path], typer.Option("--out", help="layout file (default: beside the trace, <stem>.layout.json)")] = None,
) -> None:
    """Write a Foxglove/Lichtblick layout fitted to a trace: its path in view, one plot series per vehicle."""
    from .cli import _fail, out as console

    try:
        view = read_run_view(trace)
    except ValueError as error:
        _fail(2, f"trace {trace}: {error}")
    if not view.vehicles:
        _fail(2, f"trace {trace}: records no vehicle")
    path = out or layout_path(trace)
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(json.dumps(run_layout(view.config, len(view.vehicles)), indent=2) + "\n")
    except OSError as error:
        _fail(2, f"--out {path}: cannot write the layout there: {error.strerror or error}")
    console.print(f"wrote {path}", highlight=False, soft_wrap=True)


def figure_command(
    first: Annotated[Path, typer.Argument(metavar="A.mcap", help="trace of the left column (the paper: regular law)")],
    second: Annotated[Path, typer.Argument(metavar="B.mcap", help="trace of the right column (the paper: sine law)")],
    out: Annotated[Path, typer.Option("--out", help="figure file: .pdf, .svg (vector) or .png")],
    dpi: Annotated[int, typer.Option(min=30, max=1200, help="dots per inch of a PNG (the figure is 12.4 x 15 in)")] = 150,
) -> None:
    """Draw the paper's figure pair from two traces: velocity, distance and path errors, and X-Y, side by side."""
    from .cli import _fail, _load_trace, out as console

    if out.suffix.lower() not in FIGURE_SUFFIXES:
        _fail(2, f"--out {out}: expected a file ending in {', '.join(FIGURE_SUFFIXES)}")
    from .figure import draw_pair, save

    runs = []
    for trace in (first, second):
        loaded = _load_trace(trace)
        if loaded.config is None:
            _fail(2, f"trace {trace}: has no platoon.config metadata (not written by platoon run?)")
        if not loaded.vehicles() or any(len(loaded.component(v)["t"]) == 0 for v in loaded.vehicles()):
            _fail(2, f"trace {trace}: no recorded communication point, nothing to draw "
                     f"(run {loaded.run.get('status', '?')})")
        try:
            runs.append((loaded, recorded_config(loaded.config)))
        except ValueError as error:
            _fail(2, f"trace {trace}: {error}")
    figure = draw_pair(runs)
    try:
        save(figure, out, dpi)
    except OSError as error:
        _fail(2, f"--out {out}: cannot write the figure there: {error.strerror or error}")
    console.print(f"wrote {out}", highlight=False, soft_wrap=True)


def register(app: typer.Typer) -> None:
    """Add ``layout`` and ``figure`` to ``platoon``."""
    app.command("layout")(layout_command)
    app.command("figure")(figure_command)
