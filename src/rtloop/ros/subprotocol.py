"""Accept both names of the Foxglove WebSocket protocol in front of a server that knows one.

foxglove-sdk's server accepts only the subprotocol ``foxglove.sdk.v1``; Lichtblick (the
open-source Foxglove) before late 2025 and older Foxglove apps offer ``foxglove.websocket.v1``
and get HTTP 400. The protocol under both names is the same, and a WebSocket's frames do
not carry the subprotocol: only the opening handshake names it. So :class:`SubprotocolFront`
listens where clients connect, renames the subprotocol in the client's handshake request
(and back in the server's answer), and from then on passes the bytes through unchanged to
the SDK server, which listens on the loopback interface only.
"""

from __future__ import annotations

import contextlib
import socket
import threading

SDK_SUBPROTOCOL = "foxglove.sdk.v1"
ACCEPTED_SUBPROTOCOLS = (SDK_SUBPROTOCOL, "foxglove.websocket.v1")
"""What a client may offer (``Sec-WebSocket-Protocol``); the first is what the SDK speaks."""
MAX_HANDSHAKE_BYTES = 16384
HANDSHAKE_TIMEOUT_S = 10.0


class SubprotocolFront:
    """A TCP listener on ``host:port`` relaying each connection to ``127.0.0.1:backend_port``."""

    def __init__(self, host: str, port: int, backend_port: int) -> None:
        self.backend_port = backend_port
        self.listener = socket.create_server((host, port), family=_family(host), reuse_port=False)
        self.port = self.listener.getsockname()[1]
        """The port clients connect to (the one the system gave, if 0 was asked for)."""
        self.closed = False
        self.thread = threading.Thread(target=self._accept_loop, name="rtloop-foxglove-front", daemon=True)
        self.thread.start()

    def close(self) -> None:
        self.closed = True
        with contextlib.suppress(OSError):
            self.listener.shutdown(socket.SHUT_RDWR)
        self.listener.close()

    def _accept_loop(self) -> None:
        while not self.closed:
            try:
                client, _ = self.listener.accept()
            except OSError:
                return  # closed
            threading.Thread(target=self._serve, args=(client,), name="rtloop-foxglove-client", daemon=True).start()

    def _serve(self, client: socket.socket) -> None:
        backend = None
        try:
            client.settimeout(HANDSHAKE_TIMEOUT_S)
            request, rest = _read_head(client)
            request, renamed = rename_offer(request)
            backend = socket.create_connection(("127.0.0.1", self.backend_port), timeout=HANDSHAKE_TIMEOUT_S)
            backend.sendall(request + rest)
            answer, rest = _read_head(backend)
            if renamed is not None:
                answer = _with_protocol(answer, SDK_SUBPROTOCOL, renamed)
            client.sendall(answer + rest)
            client.settimeout(None)
            backend.settimeout(None)
        except (OSError, ValueError):
            client.close()
            if backend is not None:
                backend.close()
            return
        pump = threading.Thread(target=_pipe, args=(backend, client), name="rtloop-foxglove-pump", daemon=True)
        pump.start()
        _pipe(client, backend)
        pump.join()


def rename_offer(request: bytes) -> tuple[bytes, str | None]:
    """The handshake request with ``foxglove.websocket.v1`` offered as ``foxglove.sdk.v1``.

    Returns the request and the name the client used (None: left as it was, because it
    already offers the SDK's name or offers neither — the SDK then answers as it does).
    """
    offered = _protocols(request)
    if SDK_SUBPROTOCOL in offered:
        return request, None
    for alias in ACCEPTED_SUBPROTOCOLS[1:]:
        if alias in offered:
            return _with_protocol(request, alias, SDK_SUBPROTOCOL), alias
    return request, None


def _protocols(head: bytes) -> list[str]:
    for line in head.split(b"\r\n"):
        name, colon, value = line.partition(b":")
        if colon and name.strip().lower() == b"sec-websocket-protocol":
            return [item.strip().decode("latin-1") for item in value.split(b",")]
    return []


def _with_protocol(head: bytes, old: str, new: str) -> bytes:
    """``head`` with its ``Sec-WebSocket-Protocol`` header (any case) saying ``new`` where it said ``old``."""
    lines = head.split(b"\r\n")
    for index, line in enumerate(lines):
        name, colon, _ = line.partition(b":")
        if colon and name.strip().lower() == b"sec-websocket-protocol" and old in _protocols(line):
            lines[index] = f"Sec-WebSocket-Protocol: {new}".encode()
    return b"\r\n".join(lines)


def _read_head(sock: socket.socket) -> tuple[bytes, bytes]:
    """An HTTP head (through the blank line) and whatever came after it in the same reads."""
    data = b""
    while b"\r\n\r\n" not in data:
        chunk = sock.recv(4096)
        if not chunk:
            raise ValueError("connection closed during the handshake")
        data += chunk
        if len(data) > MAX_HANDSHAKE_BYTES:
            raise ValueError("handshake too long")
    head, _, rest = data.partition(b"\r\n\r\n")
    return head + b"\r\n\r\n", rest


def _pipe(source: socket.socket, sink: socket.socket) -> None:
    """Copy bytes until either side closes, then close both (the other pump then ends too)."""
    try:
        while chunk := source.recv(65536):
            sink.sendall(chunk)
    except OSError:
        pass
    finally:
        for sock in (source, sink):
            with contextlib.suppress(OSError):
                sock.shutdown(socket.SHUT_RDWR)
            sock.close()


def _family(host: str) -> socket.AddressFamily:
    return socket.AF_INET6 if ":" in host else socket.AF_INET
