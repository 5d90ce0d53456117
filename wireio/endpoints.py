"""Opening streams: a listening server whose connections are :class:`WireStream` s, and a
client connection."""

from __future__ import annotations

import asyncio
import ssl as ssl_module
from typing import Any

from protocol import Connection

from .stream import OnConnect, WireStream


async def serve(
    on_connect: OnConnect,
    host: str | None,
    port: int,
    **kwargs: Any,
) -> asyncio.Server:
    """Listen on ``host``:``port``; each accepted connection runs ``on_connect(stream)`` as a
    task. The stream reads nothing until its owner attaches a connection and calls
    :meth:`WireStream.receive` (so TLS can still be started on it). ``kwargs`` go to
    ``loop.create_server`` (``backlog``, ``reuse_address`` ...)."""
    loop = asyncio.get_running_loop()
    return await loop.create_server(lambda: WireStream(on_connect=on_connect), host, port, **kwargs)


async def open_connection(
    host: str,
    port: int,
    conn: Connection,
    *,
    ssl: ssl_module.SSLContext | None = None,
    server_hostname: str | None = None,
    ssl_handshake_timeout: float | None = None,
) -> WireStream:
    """Connect to ``host``:``port`` (TLS with ``ssl``) and carry ``conn`` over it."""
    loop = asyncio.get_running_loop()
    tls: dict[str, Any] = {}
    if ssl is not None:
        tls = {"ssl": ssl, "ssl_handshake_timeout": ssl_handshake_timeout}
        if server_hostname is not None:
            tls["server_hostname"] = server_hostname
    _, stream = await loop.create_connection(lambda: WireStream(conn), host, port, **tls)
    return stream


__all__ = ["open_connection", "serve"]
