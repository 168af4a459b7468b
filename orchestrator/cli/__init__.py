"""The `platoon` command line: one module per command group (run, trace, bench, hil, ssp, viewer, sweep), the
helpers they share in ``common`` (and, without typer or rich, in ``plain``), the Typer app that gathers them
in ``app``, the entry point in ``launch`` (a plain `platoon run` starts without typer)."""


def main() -> None:
    """The ``platoon`` console script (orchestrator/cli/launch.py)."""
    from orchestrator.cli.launch import main as launch

    launch()


__all__ = ["main"]
