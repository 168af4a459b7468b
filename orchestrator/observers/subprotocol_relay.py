"""Let viewers that know the Foxglove WebSocket protocol only by its old name watch a live run.

foxglove-sdk's server (0.30) accepts the WebSocket subprotocol ``foxglove.sdk.v1`` only; Lichtblick
releases from before it learnt that name (the open-source Foxglove fork, e.g. 1.10.8) and other older
clients offer only ``foxglove.websocket.v1`` and are refused at the handshake ("Check that the WebSocket server ...
supports protocol version foxglove.websocket.v1"). The two are the same protocol under two names
(Foxglove's own statement, and why Lichtblick later added the new name beside the old one).

So the live view puts this small relay in front of the SDK's server: it owns the port the user
asked for, rewrites the subprotocol name in the HTTP upgrade request (old name -> new) and in the
server's answer (new -> old), and from then on copies bytes both ways unchanged. A client that offers
the new name passes untouched. The SDK's server listens on 127.0.0.1 only, on a port of its own.
"""

from __future__ import annotations

import socket
import threading
import time
from contextlib import suppress

LEGACY = b"foxglove.websocket.v1"
CURRENT = b"foxglove.sdk.v1"
HEADER = b"sec-websocket-protocol:"
MAX_HEAD = 64 * 1024  # bytes of an HTTP upgrade request or answer, at most
BUFFER = 1 << 16
DRAIN = 5.0  # s a closing relay lets each client's copy finish (what the server sent before it stopped)


def _read_head(connection: socket.socket) -> tuple[bytes, bytes]:
    """(HTTP head up to and including the blank line, bytes read after it); empty head if the peer left."""
    data = b""
    while b"\r\n\r\n" not in data:
        if len(data) > MAX_HEAD:
            return b"", b""
        chunk = connection.recv(BUFFER)
        if not chunk:
            return b"", b""
        data += chunk
    end = data.index(b"\r\n\r\n") + 4
    return data[:end], data[end:]


def _rename(head: bytes, offered: bytes, wanted: bytes, only_without: bytes | None = None) -> tuple[bytes, bool]:
    """``head`` with ``offered`` replaced by ``wanted`` in its Sec-WebSocket-Protocol header(s).

    ``only_without``: leave the head alone if that name is offered too (a client that knows the new
    name gets it as it asked). Returns (head, renamed).
    """
    lines = head.split(b"\r\n")
    names = [name.strip() for line in lines if line.lower().startswith(HEADER)
             for name in line[len(HEADER):].split(b",")]
    if offered not in names or (only_without is not None and only_without in names):
        return head, False
    renamed = []
    for line in lines:
        if line.lower().startswith(HEADER):
            values = [wanted if name.strip() == offered else name.strip() for name in line[len(HEADER):].split(b",")]
            line = line[:len(HEADER)] + b" " + b", ".join(values)
        renamed.append(line)
    return b"\r\n".join(renamed), True


def _pipe(source: socket.socket, target: socket.socket) -> None:
    with suppress(OSError):
        while chunk := source.recv(BUFFER):
            target.sendall(chunk)
    with suppress(OSError):
        target.shutdown(socket.SHUT_WR)


class SubprotocolRelay:
    """Listens on ``host:port`` (``OSError`` if it cannot, e.g. in use) and relays each client to
    ``127.0.0.1:upstream``, renaming the legacy subprotocol at the handshake."""

    def __init__(self, host: str, port: int) -> None:
        family = socket.AF_INET6 if ":" in host else socket.AF_INET
        self._listener = socket.socket(family, socket.SOCK_STREAM)
        # a run started right after another on the same port must not wait for its closed connections
        self._listener.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            self._listener.bind((host, port))
            self._listener.listen(16)
        except OSError:
            self._listener.close()
            raise
        self.port = self._listener.getsockname()[1]
        self.upstream = 0
        self._open: set[socket.socket] = set()
        self._serving: list[threading.Thread] = []
        self._lock = threading.Lock()

    def start(self, upstream: int) -> None:
        self.upstream = upstream
        threading.Thread(target=self._accept, name="live-view relay", daemon=True).start()

    def _accept(self) -> None:
        while True:
            try:
                client, _ = self._listener.accept()
            except OSError:  # closed
                return
            serving = threading.Thread(target=self._serve, args=(client,), name="live-view client", daemon=True)
            with self._lock:
                self._serving.append(serving)
            serving.start()

    def _serve(self, client: socket.socket) -> None:
        server = None
        try:
            head, rest = _read_head(client)
            if not head:
                return
            head, legacy = _rename(head, LEGACY, CURRENT, only_without=CURRENT)
            server = socket.create_connection(("127.0.0.1", self.upstream))
            self._track(client, server)
            server.sendall(head + rest)
            answer, rest = _read_head(server)
            if not answer:
                return
            if legacy:
                answer, _ = _rename(answer, CURRENT, LEGACY)
            client.sendall(answer + rest)
            upward = threading.Thread(target=_pipe, args=(client, server), daemon=True)
            upward.start()
            _pipe(server, client)
            upward.join()
        except OSError:
            pass
        finally:
            for connection in (client, server):
                if connection is not None:
                    with suppress(OSError):
                        connection.close()
            self._untrack(client, server)

    def _track(self, *connections: socket.socket) -> None:
        with self._lock:
            self._open.update(connections)

    def _untrack(self, *connections: socket.socket | None) -> None:
        with self._lock:
            self._open.difference_update(c for c in connections if c is not None)

    def close(self) -> None:
        """Stop accepting; once the SDK's server has stopped, each client's copy ends when it has passed on
        the server's last bytes (the run's last log line, its goodbye): those are let through, up to
        ``DRAIN`` s (a loaded machine had the relay drop them), then the clients still connected are dropped."""
        with suppress(OSError):
            self._listener.shutdown(socket.SHUT_RDWR)  # wakes the thread blocked in accept()
        with suppress(OSError):
            self._listener.close()
        deadline = time.monotonic() + DRAIN
        with self._lock:
            serving = list(self._serving)
        for thread in serving:
            if thread.is_alive():
                thread.join(max(0.0, deadline - time.monotonic()))
        with self._lock:
            connections, self._open = list(self._open), set()
        for connection in connections:
            with suppress(OSError):
                connection.shutdown(socket.SHUT_RDWR)
