"""Zenoh sessions for every program of the bridge: one config builder, one way to open.

The host (``bridge.live``), the m3pi emulator, the serial endpoint and the benchmarks all build their
Zenoh config here from the same three things a config or command line gives: endpoints to
``connect`` to, endpoints to ``listen`` on, and optionally a Zenoh config file (JSON5, for TLS
certificates, access control, a router mode ...). This is the one place that decides which sockets
a program of ours opens, so its rules hold for all of them:

* a session listens only on the endpoints its caller or its config file names. Zenoh's own default
  (a peer listens on ``tcp/[::]:0``: every interface, a random port) never applies, so a session that
  only connects listens nowhere;
* multicast and gossip scouting are off unless the config file turns them on;
* an endpoint that leaves the machine (not loopback, not a Unix socket) must be TLS (``tls/`` or
  ``quic/``): anyone on a shared network could otherwise publish on the robot's keys. The refusal
  names the recipe (``platoon hil-certs``, docs/hil.md "A secure lab"); ``allow_insecure`` lifts it;
* a listener others can reach (not loopback) needs more than its scheme: the effective config must ask
  every client for a certificate of the lab (mutual TLS) and deny by default (access control), checked
  before the session opens; a server certificate alone lets any client in and drive.
"""

from __future__ import annotations

import ipaddress
import json
import os
from contextlib import contextmanager
from pathlib import Path
from typing import Any, Iterator, Sequence

import zenoh

_LOG_STARTED = False
SECURE_PROTOCOLS = ("tls", "quic")  # link protocols that authenticate and encrypt (docs/hil.md)
LOCAL_PROTOCOLS = ("unixsock-stream", "unixpipe", "vsock")  # never leave the machine
RECIPE = "run `platoon hil-certs` and use tls/ endpoints with its Zenoh configs (docs/hil.md, \"A secure lab\")"


# Every Zenoh runtime of the process (app, acceptor, tx, rx, net) on one worker thread: ``one_zenoh_thread``.
ONE_THREAD_RUNTIME = ("(app: (worker_threads: 1), acc: (handover: app), tx: (handover: app), rx: (handover: app), "
                      "net: (handover: app))")


@contextmanager
def one_zenoh_thread() -> Iterator[None]:
    """Open the session of this block with the process's Zenoh on one thread, not its default five
    runtimes (rx-0, rx-1, tx-0, net-0, acc-0).

    For ``platoon serve``, whose whole Zenoh traffic is one small request and its reply at a time: with
    the default runtimes a request is read on an rx thread, answered on the callback's Python thread,
    written on the tx thread, and the idle net and acc threads are woken too, about eleven context
    switches per request; on one thread half of those, and about 30 % less of the server's CPU, which is
    what a lockstep step of many servers on 2 cores is bound by (docs/remote.md, "One round trip per
    step"). Only the server's process: a run's, or an FMI importer's hosting the client FMU, keep Zenoh's
    defaults. Zenoh reads ``ZENOH_RUNTIME`` once, when its runtime starts (the process's first session),
    so this acts only if that happens in the block; the variable is removed again afterwards (child
    processes keep the defaults). A ``ZENOH_RUNTIME`` the user set wins (an empty one counts as unset).
    """
    if os.environ.get("ZENOH_RUNTIME"):
        yield
        return
    os.environ["ZENOH_RUNTIME"] = ONE_THREAD_RUNTIME
    try:
        yield
    finally:
        os.environ.pop("ZENOH_RUNTIME", None)


class SessionError(RuntimeError):
    """Zenoh refused the config or could not open a session; the text says which endpoint or file."""


def _host(address: str) -> str:
    """The host part of ``host:port`` (IPv6 in brackets), without the port and the ``#`` / ``?`` options."""
    address = address.split("#", 1)[0].split("?", 1)[0]
    if address.startswith("["):
        return address[1:address.find("]")] if "]" in address else address
    return address.rsplit(":", 1)[0] if ":" in address else address


def is_loopback(host: str) -> bool:
    """``localhost``, 127.0.0.0/8 or ::1: traffic that never leaves this machine."""
    if host.lower() == "localhost":
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False


def insecure_endpoints(endpoints: Sequence[str]) -> list[str]:
    """The endpoints that leave the machine without TLS (a wildcard such as ``tcp/[::]:0`` leaves it too)."""
    bad = []
    for endpoint in endpoints:
        protocol, _, address = endpoint.partition("/")
        if protocol in SECURE_PROTOCOLS or protocol in LOCAL_PROTOCOLS:
            continue
        if not is_loopback(_host(address)):
            bad.append(endpoint)
    return bad


def _named_endpoints(config: zenoh.Config, section: str) -> list[str]:
    """The endpoints a config file names under ``section`` (``connect``/``listen``); [] if it names none.

    Zenoh's own default (a map by mode, e.g. ``{"peer": ["tcp/[::]:0"], ...}``) counts as none: that
    is the socket nobody asked for."""
    value: Any = json.loads(config.get_json(f"{section}/endpoints"))
    default: Any = json.loads(zenoh.Config().get_json(f"{section}/endpoints"))
    if value == default or value is None:
        return []
    if isinstance(value, dict):  # per-mode lists: the one for this session's mode
        mode = json.loads(config.get_json("mode")) or "peer"
        value = value.get(mode) or []
    return [str(endpoint) for endpoint in value]


def zenoh_config(connect: Sequence[str] = (), listen: Sequence[str] = (), config_file: str | None = None,
                 mode: str = "peer", allow_insecure: bool = False, connect_wait: float = 0.0) -> zenoh.Config:
    """A Zenoh config that opens only the sockets named here or in ``config_file`` (module docstring).

    ``config_file``'s settings win, except the endpoints named here; without a file: peer mode. A client
    cannot open without its router: ``connect_wait`` s is how long opening keeps trying (a peer opens at once
    and finds the others later)."""
    secure = [endpoint for endpoint in (*connect, *listen) if endpoint.partition("/")[0] in SECURE_PROTOCOLS]
    if secure and not config_file:  # without certificates the handshake fails, and the session waits in silence
        raise SessionError(f"endpoint {secure[0]} is TLS but no zenoh_config gives its certificates: a TLS session "
                           "needs the lab's CA and this host's certificate and key (run `platoon hil-certs` and pass "
                           "the host's file as zenoh_config / --zenoh-config; docs/hil.md, \"A secure lab\")")
    try:
        config = zenoh.Config.from_file(str(Path(config_file))) if config_file else zenoh.Config()
        if not config_file:
            config.insert_json5("mode", json.dumps(mode))
        if not config_file and mode == "client" and connect_wait > 0.0:
            config.insert_json5("connect/timeout_ms", json.dumps(round(connect_wait * 1000)))
        connect = list(connect) or _named_endpoints(config, "connect")
        listen = list(listen) or _named_endpoints(config, "listen")
        config.insert_json5("connect/endpoints", json.dumps(connect))
        config.insert_json5("listen/endpoints", json.dumps(listen))  # [] = listen nowhere
        for scouting in ("multicast", "gossip"):  # null: the file did not say; Zenoh's default would be on
            if json.loads(config.get_json(f"scouting/{scouting}/enabled")) is None:
                config.insert_json5(f"scouting/{scouting}/enabled", "false")
    except (zenoh.ZError, OSError, ValueError) as error:
        where = f"zenoh config file {config_file}" if config_file else f"endpoints connect={list(connect)} listen={list(listen)}"
        raise SessionError(f"{where}: {error}") from None
    bad = insecure_endpoints([*connect, *listen])
    if bad and not allow_insecure:
        raise SessionError(f"endpoint {bad[0]} leaves this machine without TLS: anyone on that network could "
                           f"drive or fake the robot; {RECIPE}, or set allow_insecure = true ([hil] in the config, "
                           "--allow-insecure on the robot side) on a network you trust")
    exposed = exposed_listeners(listen)
    missing = listener_problems(config) if exposed and not allow_insecure else []
    if missing:
        where = f"zenoh config file {config_file}" if config_file else "the Zenoh config (no --zenoh-config file)"
        raise SessionError(f"listening on {exposed[0]}, off this machine, needs {' and '.join(missing)} in {where}: "
                           f"else anyone who reaches it connects; {RECIPE}, or allow_insecure on a network you trust")
    return config


def session_mode(connect: Sequence[str], listen: Sequence[str]) -> str:
    """The mode of a session that meets a ROS 2 graph: "client" where it only connects, as rmw_zenoh's nodes
    connect to rmw_zenohd and a lab's programs to zenoh-bridge-ros2dds (both Zenoh routers). A peer that
    listens nowhere, connected to a router, is told of the robot's peer session and expects to reach it
    directly, so the router routes it nothing: the run saw the graph but got no pose. A client gets all
    the router routes, and reaches a peer (the emulator) as well. A session that listens is a peer."""
    return "client" if connect and not listen else "peer"


def exposed_listeners(listen: Sequence[str]) -> list[str]:
    """The listen endpoints others can reach: not loopback, not a local socket (a wildcard address is exposed)."""
    exposed = []
    for endpoint in listen:
        protocol, _, address = endpoint.partition("/")
        if protocol not in LOCAL_PROTOCOLS and not is_loopback(_host(address)):
            exposed.append(endpoint)
    return exposed


def listener_problems(config: zenoh.Config) -> list[str]:
    """What the effective config lacks for a listener others can reach: mutual TLS (every client shows a
    certificate of the lab's CA) and access control that denies by default (only the rules' hosts may put on
    the robot's keys). A server certificate alone lets any client in."""
    def value(key: str) -> Any:
        return json.loads(config.get_json(key))

    problems = []
    if value("transport/link/tls/enable_mtls") is not True or not (
            value("transport/link/tls/root_ca_certificate") or value("transport/link/tls/root_ca_certificate_base64")):
        problems.append("mutual TLS (transport.link.tls.enable_mtls = true with the lab's root_ca_certificate)")
    if value("access_control/enabled") is not True or value("access_control/default_permission") != "deny":
        problems.append("access control that denies by default (access_control.enabled, default_permission \"deny\")")
    else:
        problems += _open_puts(value("access_control"))
    return problems


def _open_puts(acl: dict[str, Any]) -> list[str]:
    """A policy of ``acl`` that allows puts or tokens in from sessions named by no certificate (or user): any
    client could then drive the robot, deny by default or not."""
    rules = {rule.get("id"): rule for rule in acl.get("rules") or []}
    subjects = {subject.get("id"): subject for subject in acl.get("subjects") or []}
    for policy in acl.get("policies") or []:
        opening = [rules.get(name) or {} for name in policy.get("rules") or []]
        opening = [rule for rule in opening if rule.get("permission") == "allow"
                   and "ingress" in (rule.get("flows") or ["ingress"])
                   and {"put", "liveliness_token"} & set(rule.get("messages") or [])]
        anyone = [name for name in policy.get("subjects") or []
                  if not ((subjects.get(name) or {}).get("cert_common_names") or (subjects.get(name) or {}).get("usernames"))]
        if opening and anyone:
            return [f"access control that lets only named hosts put (rule {opening[0].get('id')!r} lets subject "
                    f"{anyone[0]!r}, which names no certificate, put)"]
    return []


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
