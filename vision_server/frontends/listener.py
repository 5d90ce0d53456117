"""A listener that admits every connection through the service's front door before TLS, and
closes the ones that stall.

The front-end hands it a protocol factory (aiohttp's request handler, an asyncio stream
protocol) and its policy; the listener accepts raw sockets itself, so that a connection is
counted (:meth:`FrontDoor.enter`) before its TLS handshake and before anything it sends is
read. A refused connection is closed at once: it costs one accept, never a handshake.

Each admitted connection has a clock that nothing it sends can extend (:class:`Clock`):

- until it is signed in, it must complete each request within ``request_timeout_s`` of the
  connection's start or of its last answer (the TLS handshake counts);
- once signed in, it may wait ``idle_timeout_s`` between requests;
- while an answer is being written, the client must read: a write buffer that does not shrink
  for ``write_timeout_s`` drops the connection.

The front-end tells the clock when a request begins and ends (:meth:`Listener.clock_of`); a
watchdog closes what is overdue once a second. Counts per front-end and the server-wide total
are the door's (``server: max_connections_total``).
"""

from __future__ import annotations

import asyncio
import contextlib
import fcntl
import logging
import socket
import ssl
import struct
import termios
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

from ..service import FrontDoor, Pass, Refusal, failure_key, peer_host, peer_name

log = logging.getLogger("vision_server")

WATCH_INTERVAL_S = 1.0
REFUSAL_LOG_INTERVAL_S = 10.0
"""A flood is logged once per interval with its count, not once per connection."""


@dataclass(frozen=True)
class Policy:
    """What one front-end's connections may do before they are closed (seconds)."""

    name: str
    """The front-end's name in refusals, logs and the door's counts (``console``, ``line``)."""
    max_connections: int
    request_timeout_s: float
    idle_timeout_s: float
    write_timeout_s: float
    tls_handshake_timeout_s: float = 10.0
    max_unsigned_per_host: int | None = None
    """Connections one host (an IPv6 /64, all of loopback as one) may hold before any of them
    has signed in; one more from it is refused. None: no such bound (a browser opens several
    connections before it signs in). Without it, one host that reconnects in a loop holds
    every place of the front-end and nobody else can sign in."""


@dataclass
class Clock:
    """One connection's deadlines. Times are ``time.monotonic()`` seconds."""

    started: float
    transport: asyncio.BaseTransport | None = None
    host: str = ""
    """Whose connection (:func:`~vision_server.service.failure_key` of its peer)."""
    signed_in: bool = False
    busy: int = 0
    """Requests of this connection being answered now."""
    deadline: float = 0.0
    write_stalled_since: float | None = None
    write_buffered: int = 0
    requests: int = field(default=0)

    def begin(self) -> None:
        self.busy += 1
        self.requests += 1

    def end(self, policy: Policy, now: float) -> None:
        self.busy = max(0, self.busy - 1)
        wait = policy.idle_timeout_s if self.signed_in else policy.request_timeout_s
        self.deadline = now + wait

    def overdue(self, policy: Policy, now: float) -> str | None:
        """Why the connection must close now, or None."""
        transport = self.transport
        if isinstance(transport, asyncio.WriteTransport):
            buffered = unsent_bytes(transport)
            if buffered and (self.write_stalled_since is None or buffered < self.write_buffered):
                self.write_stalled_since = now
            elif not buffered:
                self.write_stalled_since = None
            self.write_buffered = buffered
            if (
                self.write_stalled_since is not None
                and now - self.write_stalled_since > policy.write_timeout_s
            ):
                return f"the client read nothing for {policy.write_timeout_s:g} s"
        if self.busy == 0 and now > self.deadline:
            if self.requests == 0 or not self.signed_in:
                return f"no complete request within {policy.request_timeout_s:g} s"
            return f"idle for {policy.idle_timeout_s:g} s"
        return None


class _OncePerInterval(logging.Filter):
    """Passes one record per ``interval_s`` (with how many were dropped since), without its
    traceback: what a client's malformed bytes make a library log must not fill the disk."""

    def __init__(self, interval_s: float) -> None:
        super().__init__()
        self.interval_s = interval_s
        self._last = -interval_s
        self._dropped = 0

    def filter(self, record: logging.LogRecord) -> bool:
        now = time.monotonic()
        if now - self._last < self.interval_s:
            self._dropped += 1
            return False
        if self._dropped:
            record.msg = f"{record.msg} ({self._dropped} more like it not logged)"
        error = record.exc_info[1] if record.exc_info else None
        if error is not None:
            record.msg = f"{record.msg}: {type(error).__name__}: {error}"
        record.exc_info = None
        record.exc_text = None
        self._last, self._dropped = now, 0
        return True


def quiet_logger(name: str, interval_s: float = REFUSAL_LOG_INTERVAL_S) -> logging.Logger:
    """A logger for a library's per-connection errors: one line per ``interval_s``, no
    tracebacks (see :class:`_OncePerInterval`)."""
    logger = logging.getLogger(name)
    if not any(isinstance(f, _OncePerInterval) for f in logger.filters):
        logger.addFilter(_OncePerInterval(interval_s))
    return logger


def unsent_bytes(transport: asyncio.WriteTransport) -> int:
    """Bytes written to ``transport`` that its client has not taken: the transport's own
    buffer and, on Linux, the socket's send queue (``TIOCOUTQ``), which fills once the
    client's receive buffer is full. A client that reads nothing makes this stop shrinking."""
    pending = transport.get_write_buffer_size()
    sock = transport.get_extra_info("socket")
    if sock is not None and hasattr(termios, "TIOCOUTQ"):
        with contextlib.suppress(OSError, ValueError):
            queued = fcntl.ioctl(sock.fileno(), termios.TIOCOUTQ, b"\0\0\0\0")
            pending += struct.unpack("i", queued)[0]
    return pending


class _Counted(asyncio.Protocol):
    """The front-end's protocol, with the door's pass given back when the connection ends.

    Every callback is passed on; anything else is looked up on the wrapped protocol."""

    def __init__(
        self,
        inner: asyncio.BaseProtocol,
        on_made: Callable[[asyncio.BaseTransport], None],
        on_lost: Callable[[], None],
    ) -> None:
        self._inner = inner
        self._on_made = on_made
        self._on_lost = on_lost

    def connection_made(self, transport: asyncio.BaseTransport) -> None:
        self._on_made(transport)  # the clock exists before the front-end sees the connection
        self._inner.connection_made(transport)

    def connection_lost(self, exc: Exception | None) -> None:
        try:
            self._inner.connection_lost(exc)
        finally:
            self._on_lost()

    def data_received(self, data: bytes) -> None:
        self._inner.data_received(data)  # type: ignore[attr-defined]

    def eof_received(self) -> bool | None:
        return self._inner.eof_received()  # type: ignore[attr-defined, no-any-return]

    def pause_writing(self) -> None:
        self._inner.pause_writing()

    def resume_writing(self) -> None:
        self._inner.resume_writing()

    def __getattr__(self, name: str) -> Any:
        return getattr(self._inner, name)


class Listener:
    """Accepts ``policy.name``'s connections on one address through ``door``; each admitted
    one is served by ``factory()``'s protocol, over TLS when ``ssl_context`` is given."""

    def __init__(
        self,
        door: FrontDoor,
        policy: Policy,
        factory: Callable[[], asyncio.BaseProtocol],
        *,
        ssl_context: ssl.SSLContext | None = None,
        refusal_message: Callable[[Refusal], bytes] | None = None,
    ) -> None:
        self.door = door
        self.policy = policy
        self.factory = factory
        self.ssl_context = ssl_context
        self.refusal_message = refusal_message
        """What a refused plain-TCP connection is sent before it is closed (None: nothing);
        a TLS one gets nothing (its handshake would cost what the refusal saves)."""
        self._sockets: list[socket.socket] = []
        self._tasks: set[asyncio.Task[None]] = set()
        self._clocks: dict[asyncio.BaseTransport, Clock] = {}
        self._pending: set[socket.socket] = set()
        self._pending_hosts: list[str] = []
        """The hosts of the connections in ``_pending`` (accepted, not yet served)."""
        self._refused_unlogged = 0
        self._last_refusal_log = 0.0
        self._stopping = False
        self._all_closed = asyncio.Event()

    # ------------------------------------------------------------------ lifecycle

    async def start(self, host: str, port: int) -> None:
        """Listen on ``host:port`` (port 0: a free one; see :attr:`address`)."""
        loop = asyncio.get_running_loop()
        infos = await loop.getaddrinfo(
            host or None, port, type=socket.SOCK_STREAM, flags=socket.AI_PASSIVE
        )
        seen: set[tuple[Any, ...]] = set()
        try:
            for family, kind, proto, _name, found in infos:
                # Port 0: every address of a host name on the port the first one got.
                address = (found[0], port, *found[2:])
                if (family, address) in seen:
                    continue
                seen.add((family, address))
                sock = socket.socket(family, kind, proto)
                self._sockets.append(sock)
                sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
                if family == socket.AF_INET6:
                    sock.setsockopt(socket.IPPROTO_IPV6, socket.IPV6_V6ONLY, 1)
                sock.bind(address)
                sock.listen(128)
                sock.setblocking(False)
                port = sock.getsockname()[1]
        except OSError:
            self._close_sockets()
            raise
        for sock in self._sockets:
            self._spawn(self._accept_loop(sock))
        self._spawn(self._watch())

    @property
    def address(self) -> tuple[str, int]:
        if not self._sockets:
            raise RuntimeError(f"the {self.policy.name} is not listening")
        host, port = self._sockets[0].getsockname()[:2]
        return str(host), int(port)

    async def stop_accepting(self) -> None:
        """Close the listening sockets; connections already served go on."""
        self._stopping = True
        for task in list(self._tasks):
            task.cancel()
        for task in list(self._tasks):
            with contextlib.suppress(asyncio.CancelledError):
                await task
        self._close_sockets()
        for sock in list(self._pending):
            sock.close()

    async def close_connections(self, settle_s: float = 1.0) -> None:
        """Abort every connection still open (after the front-end's own graceful stop), and
        give their protocols up to ``settle_s`` to see it (their tasks end on the loop)."""
        for transport in list(self._clocks):
            transport.abort()  # type: ignore[attr-defined]
        if self._clocks:
            self._all_closed.clear()
            with contextlib.suppress(TimeoutError):
                async with asyncio.timeout(settle_s):
                    await self._all_closed.wait()
        for _ in range(3):  # the protocols' own tasks finish on the next turns
            await asyncio.sleep(0)

    def clock_of(self, transport: asyncio.BaseTransport | None) -> Clock | None:
        """The clock of the connection a request came on (None: not one of this listener's)."""
        return None if transport is None else self._clocks.get(transport)

    @property
    def connections(self) -> int:
        return len(self._clocks)

    # ------------------------------------------------------------------ accepting

    def _spawn(self, coro: Any) -> None:
        task = asyncio.get_running_loop().create_task(coro)
        self._tasks.add(task)
        task.add_done_callback(self._tasks.discard)

    async def _accept_loop(self, listening: socket.socket) -> None:
        loop = asyncio.get_running_loop()
        while not self._stopping:
            try:
                sock, address = await loop.sock_accept(listening)
            except OSError as exc:  # EMFILE and the like: wait instead of spinning
                log.warning("%s: cannot accept a connection: %s", self.policy.name, exc)
                await asyncio.sleep(0.1)
                continue
            peer = peer_name(address)
            host = failure_key(peer_host(peer))
            unsigned = self.policy.max_unsigned_per_host
            if unsigned is not None and self._unsigned_from(host) >= unsigned:
                self._log_refusal(
                    Refusal(f"{unsigned} connections from {host} not signed in yet"), peer
                )
                self._refuse(sock, Refusal("too many connections from this host"))
                continue
            admitted = self.door.enter(self.policy.name, peer, limit=self.policy.max_connections)
            if isinstance(admitted, Refusal):
                self._log_refusal(admitted, peer)
                self._refuse(sock, admitted)
                continue
            self._pending.add(sock)
            self._pending_hosts.append(host)
            loop.create_task(self._serve(sock, admitted, host))

    def _unsigned_from(self, host: str) -> int:
        """Connections of ``host`` held now that have not signed in (TLS handshakes too)."""
        held = sum(1 for c in self._clocks.values() if c.host == host and not c.signed_in)
        return held + self._pending_hosts.count(host)

    async def _serve(self, sock: socket.socket, admitted: Pass, host: str = "") -> None:
        loop = asyncio.get_running_loop()
        clock = Clock(started=time.monotonic(), host=host)
        clock.deadline = clock.started + self.policy.request_timeout_s

        def made(transport: asyncio.BaseTransport) -> None:
            clock.transport = transport
            self._clocks[transport] = clock

        def lost() -> None:
            if clock.transport is not None:
                self._clocks.pop(clock.transport, None)
                if not self._clocks:
                    self._all_closed.set()
            admitted.leave()

        try:
            async with asyncio.timeout(self.policy.tls_handshake_timeout_s):
                await loop.connect_accepted_socket(
                    lambda: _Counted(self.factory(), made, lost),
                    sock,
                    ssl=self.ssl_context,
                    ssl_handshake_timeout=(
                        self.policy.tls_handshake_timeout_s if self.ssl_context else None
                    ),
                )
        except (OSError, ssl.SSLError, TimeoutError, ConnectionError) as exc:
            log.info("%s: connection from %s dropped: %s", self.policy.name, admitted.peer, exc)
            sock.close()
            admitted.leave()
            return
        finally:
            self._pending.discard(sock)
            with contextlib.suppress(ValueError):
                self._pending_hosts.remove(host)

    def _refuse(self, sock: socket.socket, refusal: Refusal) -> None:
        """Close a refused connection at once: with one short message (never waited for: a
        send that would block sends nothing) or with a reset."""
        message = None
        if self.refusal_message is not None and self.ssl_context is None:
            message = self.refusal_message(refusal)
        with contextlib.suppress(OSError):
            if message:
                sock.setblocking(False)
                sock.send(message)
                sock.shutdown(socket.SHUT_WR)
            else:  # a reset, not a FIN: nothing waits in TIME_WAIT
                sock.setsockopt(socket.SOL_SOCKET, socket.SO_LINGER, struct.pack("ii", 1, 0))
        sock.close()

    def _log_refusal(self, refusal: Refusal, peer: str) -> None:
        now = time.monotonic()
        self._refused_unlogged += 1
        if now - self._last_refusal_log >= REFUSAL_LOG_INTERVAL_S:
            log.warning(
                "%s: refused %d connection(s) (latest from %s): %s",
                self.policy.name,
                self._refused_unlogged,
                peer,
                refusal.reason,
            )
            self._refused_unlogged = 0
            self._last_refusal_log = now

    async def _watch(self) -> None:
        while True:
            await asyncio.sleep(WATCH_INTERVAL_S)
            now = time.monotonic()
            for transport, clock in list(self._clocks.items()):
                why = clock.overdue(self.policy, now)
                if why is not None:
                    log.info("%s: closing a connection: %s", self.policy.name, why)
                    transport.abort()  # type: ignore[attr-defined]

    def _close_sockets(self) -> None:
        for sock in self._sockets:
            sock.close()


__all__ = ["Clock", "Listener", "Policy", "quiet_logger", "unsent_bytes"]
