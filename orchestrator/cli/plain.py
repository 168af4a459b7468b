"""What the commands share that needs neither typer nor rich loaded: the two consoles (made on first
use), plain lines, the one-line failure, a config loaded with its errors turned into that line, the
output checks.

`platoon run` starts without typer or rich (orchestrator/cli/launch.py): ~0.1 s of imports a run
does not need unless it shows help, an error, a progress bar or a table (docs/performance.md,
"Start-up"). A plain line (ASCII, printable, nothing rich would change: no emoji code such as
``:smile:``) is written to the stream directly; anything else goes through rich, as before.

No rich markup in what we print: names, paths and config text are the user's ("[[disturbance]]",
"runs/[a]/x.mcap") and must appear as written. The one styled line (``fail``) asks for markup itself.
"""

from __future__ import annotations

import re
import sys
from contextlib import contextmanager
from pathlib import Path
from typing import TYPE_CHECKING, Iterator, Optional

from orchestrator.scenario.raw_config import ConfigError, read_config_text  # no pydantic: the models load with a config
from orchestrator.support.output import OutputError  # the one output rule (docs/output.md)
from orchestrator.support.suggest import did_you_mean

if TYPE_CHECKING:
    from rich.console import Console

    from orchestrator.scenario.config import Config

_CONSOLES: dict[bool, "Console"] = {}
_EMOJI_CODE = re.compile(r":\S*:")  # what rich may replace by an emoji (":smile:"); such a line goes through rich


def console(stderr: bool = False) -> "Console":
    """The rich console on stdout (or stderr), made once: markup off, the text is the user's."""
    if stderr not in _CONSOLES:
        from rich.console import Console

        _CONSOLES[stderr] = Console(stderr=stderr, markup=False)
    return _CONSOLES[stderr]


def say(text: str, stderr: bool = False) -> None:
    """One line, as ``console(stderr).print(text, highlight=False, soft_wrap=True)`` prints it: a plain
    ASCII line goes straight to the stream (rich would write it unchanged, on a terminal too), anything
    else through rich."""
    if stderr not in _CONSOLES and text.isascii() and text.isprintable() and not _EMOJI_CODE.search(text):
        stream = sys.stderr if stderr else sys.stdout
        stream.write(text + "\n")
        stream.flush()
        return
    console(stderr).print(text, highlight=False, soft_wrap=True)


def fail(code: int, message: str) -> None:
    """``error: MESSAGE`` on stderr (the word in bold red on a terminal), then exit ``code``."""
    from rich.markup import escape

    console(stderr=True).print(f"[bold red]error:[/] {escape(message)}", markup=True, highlight=False, soft_wrap=True)
    raise SystemExit(code)


def check_choice(option: str, value: str | None, choices: tuple[str, ...]) -> None:
    """Exit 2 with one line naming ``option`` when ``value`` is not one of ``choices`` (the nearest one
    suggested): a wrong option value is the option's error, not the config key it sets."""
    if value is None or value in choices:
        return
    fail(2, f"{option} {value!r}: expected {' or '.join(choices)}{did_you_mean(value, choices)}")


def load_config(config: Path, overrides: list[str], allow_long: bool = True,
                cached: bool = False) -> tuple["Config", str]:
    """The validated config and its text as read (stored in the trace); exit 2 naming the problem.
    ``allow_long=False`` also refuses a run above the size limits (orchestrator/scenario/limits.py).
    ``cached``: a config validated before may come back from the cache of validated configs, without
    pydantic (orchestrator/scenario/config_records.py); for the paths written for it (a plain `platoon run`)."""
    from orchestrator.scenario.limits import check_run_size
    from orchestrator.scenario.raw_config import raw_mapping

    try:
        text = read_config_text(config)
        raw = raw_mapping(text, config.stem, overrides, config.parent)
        parsed = _validated(raw, cached)
        if not allow_long:
            check_run_size(parsed)
    except ConfigError as error:
        fail(2, f"config {config}: {error}")
    from orchestrator.scenario.config_warnings import config_warnings

    for warning in config_warnings(parsed):  # valid, but probably not what was meant: the run still goes
        say(f"warning: config {config}: {warning}", stderr=True)
    return parsed, text


def _validated(raw: dict, cached: bool) -> "Config":
    """``raw`` validated by the config's models (then kept, with ``cached``), or as validated before."""
    if cached:
        from orchestrator.scenario.config_records import cached_config

        found = cached_config(raw)
        if found is not None:
            return found
    from orchestrator.support.startup import loading_a_run

    with loading_a_run():  # the pydantic models, built without garbage collection: loaded when a config is read
        from orchestrator.scenario.config import config_from_mapping

    parsed = config_from_mapping(raw)
    if cached:
        from orchestrator.scenario.config_records import store_config

        store_config(raw, parsed)
    return parsed


@contextmanager
def output_rule() -> Iterator[None]:
    """Turn a refused or failed write (orchestrator/support/output.py) into exit 2 with its one line."""
    try:
        yield
    except OutputError as error:
        fail(2, str(error))


def check_output(path: Path, overwrite: bool, protect: list[Path], what: str = "--out") -> None:
    """Exit 2 with one line if the trace ``path`` must not be replaced (trace/output.py: check_replaceable)."""
    from orchestrator.trace.output import check_replaceable

    with output_rule():
        check_replaceable(path, overwrite, protect, what)


def run_inputs(config: Path, parsed: "Config") -> list[Path]:
    """Every file a run of ``config`` (or its SSP export) reads, which its output never replaces: the config,
    the files it names (a Zenoh config), the FMUs in build/fmus (both kinds) and the sources they are
    built from."""
    from fmus.builders import DEFAULT_OUT

    from orchestrator.components.kinds import fmu_files

    return [config, *parsed.named_files(), *fmu_files(DEFAULT_OUT)]


def claim_trace(trace: Optional[Path], overwrite: bool, protect: list[Path], default):
    """Claim the trace path before any work (orchestrator/trace/output.py): exit 2 with one line if it is
    in use by another run, is a file that is not a trace (without --overwrite), is the config, or cannot
    be written."""
    from orchestrator.trace.output import claim

    with output_rule():
        return claim(trace, overwrite, protect) if trace is not None else default()
