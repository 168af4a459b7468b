"""A Foxglove/Lichtblick layout fitted to one run, and what a layout needs to know of a trace.

A static layout cannot fit both the paper's 50 m circle and the m3pi's 1 m one (the 3D panel's camera
is fixed by the layout), so each run gets its own: ``runs/x.mcap`` gets ``runs/x.layout.json`` (the
trace's stem: the pair sorts together, and the viewer's file dialog, which filters on ``.json``, shows it).
Nothing here prints: problems come back as values or one-line ``ValueError``s for the caller to show.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

from orchestrator.support.output import Kind, OutputError, check_target, write_text

if TYPE_CHECKING:
    from orchestrator.scenario.config import Config


@dataclass(frozen=True)
class RunView:
    """What a layout needs from a trace: its config and the vehicles it recorded."""

    config: "Config"
    vehicles: list[str]


def layout_path(trace: Path) -> Path:
    """The layout written beside a trace: ``runs/x.mcap`` -> ``runs/x.layout.json``."""
    return trace.with_name(trace.stem + ".layout.json")


def run_layout(config: "Config", vehicles: int) -> dict[str, Any]:
    from orchestrator.trace.foxglove import SceneSettings, layout
    from orchestrator.trace.format import link_name

    links = [link_name(direction, vehicle) for direction, vehicle in config.linked()]
    return layout(vehicles, SceneSettings.of(config), links, [f"vehicle{k}" for k in config.live_vehicles()])


@dataclass(frozen=True)
class WrittenLayout:
    """Where a run's layout went: ``path`` None when it could not be written, ``warning`` then says why (one line)."""

    path: Path | None
    warning: str | None = None


def write_run_layout(trace: Path, config: "Config") -> WrittenLayout:
    """Write the layout fitted to ``config``'s run beside ``trace``.

    A layout that cannot be written (disk full, a folder in its place) costs the user nothing of the
    run: no path, and the run's summary and exit status stand; the caller decides whether to show the
    warning (a run that failed or was stopped says only that, in its one error line).
    """
    path = layout_path(trace)
    try:  # the output rule: never a file that is not a layout, never a FIFO or device; aside, then renamed
        check_target(path, overwrite=False, protect=[trace], what="layout", kind=LAYOUT)
        write_text(path, json.dumps(run_layout(config, config.platoon.count), indent=2) + "\n", what="layout")
    except OutputError as error:
        return WrittenLayout(None, f"warning: {error}")
    return WrittenLayout(path)


def is_layout(path: Path) -> bool:
    """A ``kind`` test (support/output.py): a Foxglove layout JSON as ``run_layout`` writes it."""
    try:
        with open(path, "rb") as stream:
            head = stream.read(4096)
    except OSError:
        return False
    return head.lstrip().startswith(b"{") and b'"configById"' in head


def recorded_config(raw: Any) -> "Config":
    """The config a trace recorded; ValueError (one line) if it is invalid or held inf/NaN (no view fits those)."""
    from orchestrator.scenario.config import ConfigError
    from orchestrator.scenario.stored_config import stored_config

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

    from orchestrator.trace.format import CHANNEL_PREFIX, MAGIC, vehicle_names
    from orchestrator.trace.summary_section import metadata_records

    if not trace.is_file():
        raise ValueError("no such file")
    with open(trace, "rb") as stream:
        if stream.read(len(MAGIC)) != MAGIC:
            raise ValueError("not an MCAP file (no MCAP magic at its start)")
    try:
        with open(trace, "rb") as stream:
            reader = make_reader(stream)
            summary = reader.get_summary()
            metadata = metadata_records(reader)
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


LAYOUT = Kind("a Foxglove layout", is_layout)  # what `platoon layout` replaces without --overwrite
