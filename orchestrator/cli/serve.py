"""``platoon serve``: one FMU instance served on Zenoh, for a run elsewhere whose vehicle is remote.

A run marks vehicle K remote with ``[vehicles.K] endpoint = "remote"`` and names this server (``server``,
``connect``); the run then instantiates, initializes, steps and frees the FMU here (docs/remote.md). One
process holds one instance: a second run is refused while the first holds it, and an FMU that crashes
takes this process down, never the run's. Like the robot side, it listens only where it is told
(loopback by default), and off this machine only with the lab's mutual TLS and access control.
"""

from __future__ import annotations

import math
import threading
from pathlib import Path
from typing import Annotated, Optional

import typer

from orchestrator.cli.common import err, fail
from orchestrator.cli.hil import AllowInsecure, Endpoints, stop_on_signals

DEFAULT_LISTEN = "tcp/127.0.0.1:7447"


def _fmu_path(fmu: str, kind: Optional[str]) -> Path:
    """``fmu`` as a file, or one of ours (Vehicle, VirtualTarget, Link) built into build/fmus if stale."""
    from fmus.builders import DEFAULT_OUT, FMU_NAMES, LINK_FMU

    from orchestrator.components.kinds import FmuKindError, ensure_fmus, resolve_fmu_kind

    ours = (*FMU_NAMES, LINK_FMU)
    if fmu in ours:
        try:
            chosen = resolve_fmu_kind(kind, DEFAULT_OUT)
            return ensure_fmus(DEFAULT_OUT, chosen, (fmu,), lambda name, folder: err.print(
                f"building {name}.fmu ({chosen}) in {folder} ...", highlight=False))[fmu]
        except FmuKindError as error:
            fail(2, f"--fmus: {error}")
    path = Path(fmu)
    if not path.is_file():
        fail(2, f"{fmu}: no such FMU file (or one of ours: {', '.join(ours)})")
    return path


def serve(
    fmu: Annotated[Path, typer.Argument(metavar="FMU", help="an FMU file (FMI 2.0 or 3.0 co-simulation), or Vehicle, "
                                                           "VirtualTarget or Link (ours, built if stale)")],
    name: Annotated[str, typer.Option("--name", metavar="NAME", help="the name runs reach it by: key <prefix>/fmu/<name> "
                                                     "([vehicles.K] server in the run's config)")],
    prefix: Annotated[str, typer.Option(metavar="PREFIX", help="Zenoh key prefix")] = "platoon",
    listen: Endpoints = [],
    connect: Endpoints = [],
    zenoh_config: Annotated[Optional[Path], typer.Option(help="Zenoh config file (JSON5): TLS, access control")] = None,
    fmus: Annotated[Optional[str], typer.Option("--fmus", metavar="native|python",
                                                help="which of our FMUs (default: native where a compiler is)")] = None,
    lease: Annotated[float, typer.Option(metavar="SECONDS", help="free an instance whose run is silent this long")] = 60.0,
    allow_insecure: AllowInsecure = False,
) -> None:
    """Serve one FMU instance on Zenoh for a run whose vehicle is remote (until Ctrl-C)."""
    from bridge.fmu_wire import fmu_key
    from bridge.protocol import check_prefix
    from bridge.session import SessionError, one_zenoh_thread, open_session, zenoh_config as make_config

    from orchestrator.components.fmu import UnpackedFmu
    from orchestrator.components.fmu3 import unsupported
    from orchestrator.components.served import ServedInstance, serve as answer

    problems = check_prefix(prefix) or check_prefix(name)
    if problems:
        fail(2, f"--prefix/--name: {problems[0]}")
    if not (math.isfinite(lease) and lease > 0.0):
        fail(2, f"--lease {lease}: expected a finite number of seconds > 0")
    if not (listen or connect or zenoh_config):
        listen = [DEFAULT_LISTEN]
    path = _fmu_path(str(fmu), fmus)
    try:
        unpacked = UnpackedFmu.open(path)
    except Exception as error:  # not a zip, no model description: the user's file
        fail(2, f"{path}: not an FMU ({error})")
    problem = unsupported(unpacked.description)
    if problem:
        unpacked.cleanup()
        fail(2, f"{path}: cannot be served: {problem}")
    key = fmu_key(prefix, name)
    stop = threading.Event()
    stop_on_signals(stop)
    try:
        with one_zenoh_thread():  # about 30 % less CPU per served request (bridge/session.py)
            session = open_session(make_config(connect, listen, str(zenoh_config) if zenoh_config else None,
                                               allow_insecure=allow_insecure), f"platoon serve {name}")
    except SessionError as error:
        unpacked.cleanup()
        fail(2, str(error))
    instance = ServedInstance(unpacked, lease, on_event=lambda line: err.print(line, highlight=False))
    err.print(f"serving {path.name} ({unpacked.guid}) as {key}, listening on {', '.join(listen) or 'nothing'}"
              f"{', connected to ' + ', '.join(connect) if connect else ''}; ready", highlight=False, soft_wrap=True)
    try:
        answer(instance, session, key, stop, on_zenoh_thread=True)  # its Zenoh serves nothing else (served.py)
    finally:
        session.close()
        unpacked.cleanup()


def register(app: typer.Typer) -> None:
    app.command("serve")(serve)
