"""A minimal blocking client for the server's own command line: health checks (PING) and
administration. (The full client lives in robot_client, which the server must not import.)"""

from __future__ import annotations

import socket
import time
from collections.abc import Callable

from protocol import (
    NEED_DATA,
    SUPPORTED_VERSIONS,
    CellvisionError,
    Connection,
    ConnectionClosed,
    Error,
    Hello,
    Message,
    Role,
)


class AdminError(Exception):
    """The server could not be reached or did not answer as expected."""


def call(
    host: str,
    port: int,
    build: Callable[[int], Message],
    *,
    auth_token: str | None = None,
    timeout_s: float = 5.0,
) -> Message:
    """Connect, handshake, send ``build(request_id)``, return its answer (an ERROR raises the
    matching :class:`protocol.CellvisionError`)."""
    conn = Connection(Role.CLIENT, versions=SUPPORTED_VERSIONS)
    deadline = time.monotonic() + timeout_s
    try:
        sock = socket.create_connection((host, port), timeout=timeout_s)
    except OSError as exc:
        raise AdminError(f"cannot connect to {host}:{port}: {exc}") from None
    with sock:
        try:
            sock.sendall(conn.send(Hello(1, SUPPORTED_VERSIONS, "vision-server-admin", auth_token)))
            _answer(sock, conn, deadline)
            sock.sendall(conn.send(build(2)))
            return _answer(sock, conn, deadline)
        except OSError as exc:
            raise AdminError(f"connection to {host}:{port} failed: {exc}") from None


def _answer(sock: socket.socket, conn: Connection, deadline: float) -> Message:
    while True:
        event = conn.next_event()
        if isinstance(event, Error):
            raise event.to_exception()
        if isinstance(event, Message):
            return event
        if isinstance(event, ConnectionClosed):
            raise AdminError("the server closed the connection without answering")
        assert event is NEED_DATA
        remaining = deadline - time.monotonic()
        if remaining <= 0:
            raise AdminError("no answer in time")
        sock.settimeout(remaining)
        try:
            conn.receive_data(sock.recv(1 << 20))
        except TimeoutError:
            raise AdminError("no answer in time") from None
        except CellvisionError:
            raise


__all__ = ["AdminError", "call"]
