"""An asyncio ``BufferedProtocol`` that carries one :class:`protocol.Connection`.

Received bytes go from the socket (or from asyncio's TLS layer, which decrypts into the buffer
it is given) straight into :meth:`Connection.get_buffer`: an image's pixels land in the frame
body its message views, with no intermediate ``bytes`` objects. Reading is pulled by the owner:
the stream reads a frame's header alone, then waits until the owner has looked at it (the
connection admits a frame at its header) before it reads the body, which it reads to its last
byte, then the next header. So at most one frame and the next header are read beyond what the
owner has seen; a connection whose owner does not ask for more stops there, and TCP's own flow
control holds the peer back (backpressure), as when the owner pauses reading explicitly.

Sending takes a list of buffers (:meth:`Connection.send_parts`): nothing is joined. asyncio's
plain socket transport of Python 3.11 joins in ``writelines``, so the parts are written one by
one there (each is sent from the caller's memory; what the kernel does not take at once is
copied into the transport's buffer, counted in :attr:`WireStream.write_copied_bytes`); the TLS
transport keeps the views until it has encrypted them.
"""

from __future__ import annotations

import asyncio
import logging
import ssl
from collections.abc import Awaitable, Callable, Iterable
from typing import Any, cast

from protocol import Connection
from protocol.frames import Blob, blob_view

from .framing import FrameCursor

log = logging.getLogger("wireio")

EARLY_BUFFER_BYTES = 64 * 1024
"""The read buffer for bytes that arrive before a connection is attached (a TLS client's first
data can come with the end of the handshake)."""

OnConnect = Callable[["WireStream"], Awaitable[None]]
WriteObserver = Callable[[memoryview], None]


class WireStream(asyncio.BufferedProtocol):
    """One TCP (or TLS) connection carrying a :class:`protocol.Connection`.

    The owner attaches its connection (here or with :meth:`attach`), then loops: ``await
    receive()``, then ``conn.next_event()`` until ``NEED_DATA``. It sends with
    :meth:`writelines` (``conn.send_parts(message)``) and :meth:`drain`.

    ``on_connect`` (server side): started as a task with this stream once the transport is
    made; its failure is logged and the connection aborted. ``lookahead``: see
    :class:`FrameCursor` (the default reads each header alone).
    """

    def __init__(
        self,
        conn: Connection | None = None,
        *,
        on_connect: OnConnect | None = None,
        lookahead: int | None = None,
    ) -> None:
        self._loop = asyncio.get_running_loop()
        self._conn = conn
        self._on_connect = on_connect
        self._owner_task: asyncio.Task[None] | None = None
        self._transport: asyncio.Transport | None = None
        self._switching = False
        """True while start_tls swaps the transport: reading is not switched then."""
        self._cursor = FrameCursor() if lookahead is None else FrameCursor(lookahead)
        self._gate = True
        """Read nothing until the owner has seen what was delivered (and has asked at all)."""
        self._paused_by_owner = False
        self._fresh = 0
        """Bytes delivered to the connection that no receive() has returned yet."""
        self._eof = False
        self._error: BaseException | None = None
        self._lost = False
        self._closed: asyncio.Future[None] = self._loop.create_future()
        self._waiter: asyncio.Future[None] | None = None
        self._write_paused = False
        self._drain_waiters: list[asyncio.Future[None]] = []
        self._view: memoryview | None = None
        self._early_buffer: bytearray | None = None
        self._early = bytearray()
        self.on_write: WriteObserver | None = None
        """Called with each buffer handed to the transport, in order (tests and benchmarks
        count copies with it)."""
        self.received_bytes = 0
        self.sent_bytes = 0
        self.write_copied_bytes = 0
        """Bytes the transport copied into its own buffer because the kernel did not take them
        at once (asyncio's plain socket transport; 0 for TLS, which keeps views)."""

    # ------------------------------------------------------------------ the owner's side

    @property
    def conn(self) -> Connection | None:
        return self._conn

    def attach(self, conn: Connection) -> None:
        """Carry ``conn`` from now on; bytes that came before are handed to it (copied)."""
        if self._conn is not None:
            raise RuntimeError("this stream carries a connection already")
        self._conn = conn
        if self._early:
            conn.receive_data(self._early)
            self._early = bytearray()
        if self._eof:
            conn.receive_data(b"")

    @property
    def transport(self) -> asyncio.Transport | None:
        return self._transport

    async def receive(self) -> int:
        """Wait until bytes from the peer have gone into the connection since the last call;
        how many (0: the peer closed its side, and the connection has been told).

        Call it again only after ``next_event()`` returned ``NEED_DATA``: the stream reads a
        frame's body only once its header has been seen. Raises the OSError that broke the
        connection, once what arrived before it has been returned.
        """
        if self._waiter is not None:
            raise RuntimeError("receive() is already being awaited on this stream")
        while True:
            if self._fresh:
                fresh, self._fresh = self._fresh, 0
                return fresh
            if self._eof:
                return 0
            if self._error is not None:
                raise self._error
            if self._lost:
                return 0
            self._gate = False
            self._apply_reading()
            waiter = self._loop.create_future()
            self._waiter = waiter
            try:
                await waiter
            finally:
                self._waiter = None

    def pause_reading(self) -> None:
        """Read nothing more until :meth:`resume_reading` (TCP backpressure on the peer)."""
        self._paused_by_owner = True
        self._apply_reading()

    def resume_reading(self) -> None:
        self._paused_by_owner = False
        self._apply_reading()

    @property
    def reading_paused(self) -> bool:
        """True while the owner has paused reading."""
        return self._paused_by_owner

    def write(self, data: Blob) -> None:
        self.writelines((data,))

    def writelines(self, parts: Iterable[Blob]) -> None:
        """Send ``parts`` in order without joining them; the buffers must not change until
        :meth:`drain` returns."""
        transport = self._transport
        if transport is None:
            raise RuntimeError("the stream is not connected")
        views = [view for view in map(blob_view, parts) if len(view)]
        if self.on_write is not None:
            for view in views:
                self.on_write(view)
        self.sent_bytes += sum(len(view) for view in views)
        if type(transport).writelines is asyncio.WriteTransport.writelines:
            # The base class joins the parts into one bytes object: write each instead. The
            # transport sends from our buffer at once when its own buffer is empty.
            for view in views:
                before = transport.get_write_buffer_size()
                transport.write(view)
                self.write_copied_bytes += max(transport.get_write_buffer_size() - before, 0)
        else:
            transport.writelines(views)

    async def drain(self) -> None:
        """Wait until the transport's buffer is below its high-water mark; ConnectionResetError
        once the connection is lost."""
        transport = self._transport
        if transport is not None and transport.is_closing() and not self._lost:
            # Let connection_lost run first, as asyncio's StreamWriter does.
            await asyncio.sleep(0)
        if self._lost:
            raise ConnectionResetError("connection lost")
        if not self._write_paused:
            return
        waiter = self._loop.create_future()
        self._drain_waiters.append(waiter)
        try:
            await waiter
        finally:
            self._drain_waiters.remove(waiter)

    def is_closing(self) -> bool:
        return self._transport is None or self._transport.is_closing()

    def close(self) -> None:
        if self._transport is not None:
            self._transport.close()

    def abort(self) -> None:
        if self._transport is not None:
            self._transport.abort()

    async def wait_closed(self) -> None:
        await asyncio.shield(self._closed)

    def get_extra_info(self, name: str, default: Any = None) -> Any:
        if self._transport is None:
            return default
        return self._transport.get_extra_info(name, default)

    async def start_tls(
        self,
        context: ssl.SSLContext,
        *,
        server_side: bool,
        server_hostname: str | None = None,
        ssl_handshake_timeout: float | None = None,
    ) -> None:
        """Wrap the connection in TLS (asyncio's TLS layer decrypts into our buffers)."""
        transport = self._transport
        if transport is None:
            raise RuntimeError("the stream is not connected")
        self._switching = True
        try:
            wrapped = await self._loop.start_tls(
                transport,
                self,
                context,
                server_side=server_side,
                server_hostname=server_hostname,
                ssl_handshake_timeout=ssl_handshake_timeout,
            )
        except BaseException:
            # start_tls closed the socket; its end may never reach this protocol.
            self._connection_gone(ConnectionResetError("the TLS handshake failed"))
            raise
        finally:
            self._switching = False
        if wrapped is None:
            self._connection_gone(ConnectionResetError("connection lost during TLS handshake"))
            raise ConnectionResetError("connection lost during the TLS handshake")
        self._transport = wrapped
        self._apply_reading()

    # ------------------------------------------------------------------ asyncio's side

    def connection_made(self, transport: asyncio.BaseTransport) -> None:
        self._transport = cast(asyncio.Transport, transport)
        self._apply_reading()  # nothing is read until the owner asks
        if self._on_connect is not None:
            self._owner_task = self._loop.create_task(self._run_owner(self._on_connect))

    def get_buffer(self, sizehint: int) -> memoryview:
        if self._conn is not None:
            view = self._conn.get_buffer()
        else:
            if self._early_buffer is None:
                self._early_buffer = bytearray(EARLY_BUFFER_BYTES)
            view = memoryview(self._early_buffer)
        self._view = view[: self._cursor.want(len(view))]
        return self._view

    def buffer_updated(self, nbytes: int) -> None:
        view, self._view = self._view, None
        if view is None or nbytes <= 0:
            return
        boundary = self._cursor.advance(view[:nbytes])
        if self._conn is not None:
            self._conn.buffer_updated(nbytes)
        else:
            self._early += view[:nbytes]
        self._fresh += nbytes
        self.received_bytes += nbytes
        if boundary:
            self._gate = True
        self._apply_reading()
        self._wake()

    def eof_received(self) -> bool:
        self._end_of_stream()
        # Keep our sending side open: answers may still go out after the peer's EOF (TCP
        # half-close). asyncio's TLS layer cannot do that and warns when asked.
        return self.get_extra_info("sslcontext") is None

    def connection_lost(self, exc: Exception | None) -> None:
        self._connection_gone(exc)

    def pause_writing(self) -> None:
        self._write_paused = True

    def resume_writing(self) -> None:
        self._write_paused = False
        for waiter in self._drain_waiters:
            if not waiter.done():
                waiter.set_result(None)

    # ------------------------------------------------------------------ internals

    async def _run_owner(self, on_connect: OnConnect) -> None:
        try:
            await on_connect(self)
        except Exception:
            log.exception("the connection's handler failed; closing the connection")
            self.abort()

    def _apply_reading(self) -> None:
        transport = self._transport
        if transport is None or self._switching or transport.is_closing():
            return
        if self._gate or self._paused_by_owner or self._eof:
            transport.pause_reading()
        else:
            transport.resume_reading()

    def _wake(self) -> None:
        if self._waiter is not None and not self._waiter.done():
            self._waiter.set_result(None)

    def _end_of_stream(self) -> None:
        if self._eof:
            return
        self._eof = True
        if self._conn is not None:
            self._conn.receive_data(b"")
        self._wake()

    def _connection_gone(self, exc: BaseException | None) -> None:
        if self._lost:
            return
        self._lost = True
        if exc is None:
            self._end_of_stream()
        else:
            self._error = exc
        self._wake()
        for waiter in self._drain_waiters:
            if not waiter.done():
                if exc is None:
                    waiter.set_result(None)
                else:
                    waiter.set_exception(exc)
        if not self._closed.done():
            self._closed.set_result(None)


__all__ = ["EARLY_BUFFER_BYTES", "OnConnect", "WireStream", "WriteObserver"]
