"""Whether the far side of a plain ``tcp/`` endpoint speaks TLS: the cause of a robot that never appears
when the run connects with ``tcp/`` to a robot side that listens with ``tls/`` (Zenoh's TCP link sends its
first message into a TLS server, which drops it; neither side says why, and the run only sees nothing).

The probe opens one TCP connection and offers a TLS handshake, verifying nothing (it reads no data and sends
none beyond the handshake): a TLS server answers with its hello, or an alert (a mutual-TLS one asks for the
certificate we do not have); a Zenoh TCP listener sends no TLS record back. Only what the endpoint named is
connected to, and only after the robot did not appear: nothing listens, nothing is probed otherwise.
"""

from __future__ import annotations

import socket
import ssl

PROBE_TIMEOUT = 1.0  # s: a server on this machine or a lab's LAN answers a hello in milliseconds


def tcp_address(endpoint: str) -> tuple[str, int] | None:
    """``(host, port)`` of a ``tcp/HOST:PORT`` Zenoh endpoint (IPv6 in brackets, Zenoh's ``?``/``#`` options
    cut off), or None for another scheme or a malformed one."""
    if not endpoint.startswith("tcp/"):
        return None
    locator = endpoint[len("tcp/"):].split("?", 1)[0].split("#", 1)[0]
    host, _, port = locator.rpartition(":")
    if not host or not port.isdigit():
        return None
    return host.strip("[]"), int(port)


def speaks_tls(host: str, port: int, timeout: float = PROBE_TIMEOUT) -> bool:
    """True when ``host:port`` answers a TLS handshake as a TLS server (a completed handshake, or a TLS alert
    such as "certificate required"); False for anything else (refused, closed, silent, not TLS)."""
    context = ssl.SSLContext(ssl.PROTOCOL_TLS_CLIENT)
    context.check_hostname = False
    context.verify_mode = ssl.CERT_NONE
    try:
        with socket.create_connection((host, port), timeout=timeout) as raw, context.wrap_socket(raw) as tls:
            tls.settimeout(timeout)
            return True
    except ssl.SSLError as error:  # an alert is a TLS server's refusal; EOF or garbage is not TLS
        return "ALERT" in str(error.reason or "").upper()
    except OSError:
        return False


def tls_listeners(connect: list[str] | tuple[str, ...]) -> list[str]:
    """The plain ``tcp/`` endpoints of ``connect`` whose far side speaks TLS."""
    found = []
    for endpoint in connect:
        address = tcp_address(endpoint)
        if address is not None and speaks_tls(*address):
            found.append(endpoint)
    return found
