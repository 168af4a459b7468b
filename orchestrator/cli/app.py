"""The ``platoon`` command: the Typer app that gathers the command groups, and the console entry point.

Exit codes: 0 success; 1 a run failed (the trace up to the failure is kept), or a trace held nothing
recoverable; 2 bad input (config, option or file), with one line naming what is wrong and no
traceback; 130 a run stopped by SIGINT (Ctrl-C) and 143 by SIGTERM (128 + the signal number, as a
shell reports a process killed by it), its trace finalized up to the stop.
"""

from __future__ import annotations

from typing import Annotated

import typer

from orchestrator.cli import bench, calibrate, hil, mocap, run, serve, ssp, sweep, trace, viewer
from orchestrator.cli.common import out
from orchestrator.cli.process import run_and_exit

app = typer.Typer(
    add_completion=False,
    no_args_is_help=True,
    help="Platoon co-simulation: trajectory-shaping guidance FMUs, config-driven runs, MCAP traces.",
)


def _print_version(value: bool) -> None:
    if value:
        from orchestrator.support.versions import version_line

        out.print(version_line(), highlight=False)
        raise typer.Exit()


@app.callback()
def _options(
    version: Annotated[bool, typer.Option("--version", callback=_print_version, is_eager=True,
                                          help="print the version (and of the FMUs, FMPy, pythonfmu, Python) and exit")] = False,
) -> None:
    """Platoon co-simulation: trajectory-shaping guidance FMUs, config-driven runs, MCAP traces."""


# the order `platoon --help` lists them in: a run's life first, then the robot, campaigns, other tools, views
for command in (run.build, run.run, trace.report, trace.export, run.analyze, trace.stability):
    app.command()(command)
hil.register(app)  # m3pi-emulator, m3pi-serial
calibrate.register(app)  # calibrate, compare: a live robot against its model
mocap.register(app)  # mocap: rigid bodies as robot poses
serve.register(app)  # serve: an FMU instance for a run elsewhere (remote vehicles)
sweep.register(app)  # sweep, sweep-plot, stability-map
ssp.register(app)  # export-ssp: the platoon for other tools
viewer.register(app)  # layout, figure: what users look at
trace.register_group(app)  # trace recover
bench.register(app)  # bench ...


def main() -> None:
    """Console entry point with every command through typer (orchestrator/cli/launch.py is the one that
    starts `platoon run` without it): run the command, then leave without interpreter teardown."""
    run_and_exit(app)


class _PlainHelp:
    """``--help`` as its source says it: flags without a ``<bool>`` after them (a flag takes no value, and a
    newcomer reading ``--quiet <bool>`` would type ``--quiet true``), and square brackets kept. typer reads
    help texts as rich markup, which drops ``[release]`` from ``pip install 'platoon-cosim[release]'`` and
    ``[[disturbance]]`` from a config key; our help texts are plain text, so their brackets are escaped once,
    when the command is made (the group's list of commands shows the escaped text too)."""

    def __init__(self, *args, **kwargs):  # type: ignore[no-untyped-def]
        super().__init__(*args, **kwargs)  # type: ignore[call-arg]
        if getattr(self, "rich_markup_mode", None) == "rich":  # rich renders the help (else click, plainly)
            from rich.markup import escape

            for owner in (self, *self.params):  # type: ignore[attr-defined]
                for name in ("help", "short_help", "epilog"):
                    text = getattr(owner, name, None)
                    if isinstance(text, str):
                        setattr(owner, name, escape(text))

    def get_params(self, ctx):  # type: ignore[no-untyped-def]
        params = super().get_params(ctx)  # type: ignore[misc]
        for param in params:
            if getattr(param, "is_flag", False) and param.metavar is None:
                param.metavar = " "  # shown instead of the type: nothing
        return params


class _PlainHelpCommand(_PlainHelp, typer.core.TyperCommand):
    pass


class _PlainHelpGroup(_PlainHelp, typer.core.TyperGroup):
    pass


def _plain_help(typer_app: typer.Typer) -> None:
    """Every command and group of ``typer_app`` (and its sub-apps) shows its help plainly (``_PlainHelp``)."""
    def default(cls: object, base: type) -> bool:  # not chosen by whoever declared it: typer's default
        return cls is None or cls is base or isinstance(cls, typer.models.DefaultPlaceholder)

    if default(typer_app.info.cls, typer.core.TyperGroup):
        typer_app.info.cls = _PlainHelpGroup
    for command in typer_app.registered_commands:
        if default(command.cls, typer.core.TyperCommand):
            command.cls = _PlainHelpCommand
    for group in typer_app.registered_groups:
        if default(group.cls, typer.core.TyperGroup):
            group.cls = _PlainHelpGroup
        if group.typer_instance is not None:
            _plain_help(group.typer_instance)


_plain_help(app)

