"""Every `platoon ... --help` shows what its source says: the square brackets of a help text (an extra in
``pip install 'platoon-cosim[release]'``, a config's ``[[disturbance]]``, a ``[vehicles.K]`` table) are
text, not rich markup to drop; and an 80-column terminal shows every option's name whole.

The expected texts are read from the source (each command's docstring, each option's ``help=`` and
``metavar=``), not from the click objects typer makes of them, so the test holds the rendering to the
source whatever is done to the text on the way."""

from __future__ import annotations

import inspect
import re
import typing
from typing import Any

import pytest
import typer
from typer.models import ParameterInfo
from typer.testing import CliRunner

from orchestrator.cli.app import app

WIDTH = 80  # a plain terminal; every help is rendered at this width
BRACKETED = re.compile(r"\[+[^\[\]]*\]+")  # "[release]", "[[disturbance]]", "STEPS[,...]"'s "[,...]"
FRAME = re.compile(r"[\s│╭╮╰╯─]")  # what rich adds around and inside a wrapped text: removed before comparing


def command_name(info: Any) -> str:
    return info.name or info.callback.__name__.replace("_", "-")


def source_texts(callback: Any) -> tuple[str, list[str]]:
    """A command's docstring, and the help and metavar texts of its shown parameters, as written."""
    texts = []
    for hint in typing.get_type_hints(callback, include_extras=True).values():
        for meta in getattr(hint, "__metadata__", ()):
            if isinstance(meta, ParameterInfo) and not getattr(meta, "hidden", False):
                texts += [text for text in (meta.help, meta.metavar) if text]
    return inspect.getdoc(callback) or "", texts


def every_source(typer_app: typer.Typer, path: tuple[str, ...] = ()) -> dict[tuple[str, ...], tuple[str, list[str]]]:
    """Command path -> its source texts, for every command and group of ``typer_app``."""
    found = {}
    for info in typer_app.registered_commands:
        if not info.hidden:
            found[(*path, command_name(info))] = source_texts(info.callback)
    for group in typer_app.registered_groups:
        instance = group.typer_instance
        assert instance is not None
        name = group.name or instance.info.name
        callback = instance.registered_callback.callback if instance.registered_callback else None
        found[(*path, name)] = (group.help or instance.info.help or inspect.getdoc(callback) or "", [])
        found.update(every_source(instance, (*path, name)))
    return found


def rendered(path: tuple[str, ...]) -> str:
    result = CliRunner().invoke(app, [*path, "--help"], env={"COLUMNS": str(WIDTH), "NO_COLOR": "1", "TERM": "dumb"})
    assert result.exit_code == 0 and result.exception is None, (path, result.output)
    return result.output


SOURCES = every_source(app)


def test_the_walk_finds_every_command() -> None:
    """The source walk reaches what a user reaches (the click tree typer builds)."""
    from tests.test_cli_face import every_command

    assert {tuple(path) for path in every_command() if path} == set(SOURCES)


@pytest.mark.parametrize("path", sorted(SOURCES), ids=" ".join)
def test_every_help_shows_the_brackets_its_source_writes(path: tuple[str, ...]) -> None:
    doc, option_texts = SOURCES[path]
    shown = FRAME.sub("", rendered(path))
    for text in [doc, *option_texts]:
        for bracketed in BRACKETED.findall(text):
            assert FRAME.sub("", bracketed) in shown, (path, bracketed, text)
    if path[:-1] == ():  # the command list of `platoon --help` shows the first paragraph of each docstring too
        listing = FRAME.sub("", rendered(()))
        for bracketed in BRACKETED.findall(doc.split("\n\n")[0]):
            assert FRAME.sub("", bracketed) in listing, (path, bracketed)


def test_the_helps_that_lost_their_brackets_show_them() -> None:
    """What a newcomer met: an install extra, a config table and a key pattern, gone from the help."""
    assert "'platoon-cosim[release]'" in FRAME.sub("", rendered(("build",)))
    assert "[[disturbance]]" in FRAME.sub("", rendered(("stability",)))
    assert "[vehicles.K.ros2]" in FRAME.sub("", rendered(("m3pi-emulator",)))


def click_command(path: tuple[str, ...]) -> Any:
    command = typer.main.get_command(app)
    for name in path:
        command = command.commands[name]  # type: ignore[attr-defined]
    return command


@pytest.mark.parametrize("path", sorted(SOURCES), ids=" ".join)
def test_an_80_column_terminal_shows_every_option_name_whole(path: tuple[str, ...]) -> None:
    """Rich cuts a name too long for its column with an ellipsis (``--no-string-stabil…``): a newcomer
    cannot type what the help does not show."""
    shown = rendered(path)
    words = set(re.findall(r"-[-\w]+", shown))  # every option-like word, as printed
    for param in click_command(path).params:
        if not getattr(param, "hidden", False):
            for name in [*param.opts, *param.secondary_opts]:
                if name.startswith("-"):
                    assert name in words, (path, name, [line for line in shown.splitlines() if "…" in line])


def test_analyze_keeps_its_old_flag_name_as_a_hidden_alias() -> None:
    """`--no-measure` was `--no-string-stability` (cut to `--no-string-stabil…` at 80 columns); scripts and
    notes that use the old name still work, and the help shows only the new one."""
    from tests.test_viewer import PAPER

    def analyze(*flags: str) -> str:
        result = CliRunner().invoke(app, ["analyze", str(PAPER), *flags], env={"COLUMNS": str(WIDTH)})
        assert result.exit_code == 0, result.output
        return result.output

    asks = "the config has no [[disturbance]]"  # the measured part's answer for a config without one
    assert asks in analyze() and asks in analyze("--measure") and asks in analyze("--string-stability")
    for flag in ("--no-measure", "--no-string-stability"):
        output = analyze(flag)
        assert asks not in output and "speed chain" in output, (flag, output)
    assert "string-stability" not in rendered(("analyze",))
