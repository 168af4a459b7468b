"""`platoon run`'s parsed command line, apart from what runs it: the fast start (orchestrator/cli/launch.py)
builds it before anything heavy is imported, the typer command (orchestrator/cli/run.py) builds the same."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Optional


@dataclass(frozen=True)
class RunOptions:
    """`platoon run`'s arguments and options, with the defaults its command line has."""

    config: Path
    trace: Optional[Path] = None
    overrides: list[str] = field(default_factory=list)
    monolithic: bool = False
    compare: bool = False
    quiet: bool = False
    trace_every: Optional[int] = None
    engine_name: Optional[str] = None
    fmu_kind: Optional[str] = None
    trace_writer: str = "auto"
    overwrite: bool = False
    verbose: bool = False
    allow_long: bool = False
    live: bool = False
    live_port: int = 8765
    live_host: str = "127.0.0.1"
    live_speed: float = 1.0
    live_wait: bool = False
