"""The `platoon` command line: one module per command group (run, trace, bench, hil, ssp, viewer, sweep), the
helpers they share in ``common``, the Typer app that gathers them in ``app``."""

from orchestrator.cli.app import main

__all__ = ["main"]
