"""Zenoh sessions for every program of the bridge: one config builder, one way to open.

The host (``bridge.live``), the m3pi emulator and the serial endpoint all build their Zenoh config
here from the same three things a config or command line gives: endpoints to ``connect`` to,
endpoints to ``listen`` on, and optionally a Zenoh config file (JSON5, for TLS certificates, access
control, a router mode ...). Without a file, multicast scouting is off, so a run talks only to the
endpoints it names (tests and the shipped configs use tcp/127.0.0.1 only).
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any, Sequence

import zenoh

_LOG_STARTED = False


class SessionError(RuntimeError):
    """Zenoh refused the config or could not open a session; the text says which endpoint or file."""


def zenoh_config(connect: Sequence[str] = (), listen: Sequence[str] = (), config_file: str | None = None,
                 mode: str = "peer") -> zenoh.Config:
    """A Zenoh config: ``config_file`` if given (its settings win, except the endpoints named here),
    else peer mode with multicast scouting off."""
    try:
        if config_file:
            config = zenoh.Config.from_file(str(Path(config_file)))
        else:
            config = zenoh.Config()
            config.insert_json5("mode", json.dumps(mode))
            config.insert_json5("scouting/multicast/enabled", "false")
            config.insert_json5("scouting/gossip/enabled", "false")
        if connect:
            config.insert_json5("connect/endpoints", json.dumps(list(connect)))
        if listen:
            config.insert_json5("listen/endpoints", json.dumps(list(listen)))
    except (zenoh.ZError, OSError, ValueError) as error:
        where = f"zenoh config file {config_file}" if config_file else f"endpoints connect={list(connect)} listen={list(listen)}"
        raise SessionError(f"{where}: {error}") from None
    return config


def open_session(config: zenoh.Config, what: str) -> zenoh.Session:
    """Open a session; a failure (port taken, bad endpoint) names ``what`` opened it."""
    global _LOG_STARTED
    if not _LOG_STARTED:
        zenoh.init_log_from_env_or("error")
        _LOG_STARTED = True
    try:
        return zenoh.open(config)
    except zenoh.ZError as error:
        raise SessionError(f"{what}: cannot open a Zenoh session: {error}") from None


def undeclare_all(resources: list[Any]) -> None:
    """Undeclare publishers, subscribers and tokens, newest first, and empty the list; one already gone (its
    session closed) is skipped, so that closing never fails half-way."""
    for resource in reversed(resources):
        try:
            resource.undeclare()
        except zenoh.ZError:
            pass
    resources.clear()
