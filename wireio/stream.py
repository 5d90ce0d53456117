"""An asyncio ``BufferedProtocol`` that carries one :class:`protocol.Connection`.

Received bytes go from the socket (or from asyncio's TLS layer, which decrypts into the buffer
it is given) straight into :meth:`Connection.get_buffer`: an image's pixels land in the frame
body its message views, with no intermediate ``bytes`` objects.

Between frames the stream reads whatever has arrived (up to :data:`READ_BUFFER_BYTES` a read,
so pipelined small frames come together) into a buffer of its own and hands complete frames
and headers to the connection. A large body (more than :data:`DIRECT_BODY_MIN` bytes still to
come) is read into the buffer the connection makes for it once the owner has seen its header
(the connection admits a frame at its header): reading waits for the owner there, and the
body's first bytes that came along with the header are held back until then and copied into
the body once. Reading also waits once :data:`UNSEEN_BYTES_MAX`
bytes have come that the owner has not seen, and while the owner has paused it; then TCP's
own flow control holds the peer back (backpressure).

Sending takes a list of buffers (:meth:`Connection.send_parts`): nothing is joined. asyncio's
plain socket transport of Python 3.11 joins in ``writelines``, so when its buffer is empty the
parts go out in one ``writev`` from the caller's memory; what the kernel does not take at once
is handed to the transport, which copies it into its buffer (counted in
:attr:`WireStream.write_copied_bytes`). uvloop's transports gather the parts themselves; the TLS
transport keeps the views until it has encrypted them.
"""

from __future__ import annotations

import asyncio
import logging
import os
import ssl
from collections.abc import Awaitable, Callable, Iterable
from typing import Any, cast

from protocol import Connection
from protocol.frames import Blob, blob_view

from .framing import FrameCursor

log = logging.getLogger("wireio")

READ_BUFFER_BYTES = 64 * 1024
"""The most one read between frames takes: what comes before a frame body (headers, small
frames), and at most this much of a large body's first bytes, which are then copied once."""
DIRECT_BODY_MIN = 64 * 1024
"""A body with more than this still to come is read straight into its own buffer (reading
waits for the owner to admit its header first); a smaller rest comes with the reads between
frames (and is copied on its way, as small frames are)."""
IOV_MAX = 1024
"""The most buffers one writev takes (Linux's IOV_MAX); a message has a handful."""
INTERRUPTED = -1
"""What :meth:`WireStream.receive` returns after :meth:`WireStream.interrupt`."""
UNSEEN_BYTES_MAX = 256 * 1024
"""Reading between frames stops once this much has been read that the owner has not seen."""

OnConnect = Callable[["WireStream"], Awaitable[None]]
WriteObserver = Callable[[memoryview], None]


class WireStream(asyncio.BufferedProtocol):
    """One TCP (or TLS) connection carrying a :class:`protocol.Connection`.

    The owner attaches its connection (here or with :meth:`attach`), then loops: ``await
    receive()``, then ``conn.next_event()`` until ``NEED_DATA``. It sends with
    :meth:`writelines` (``conn.send_parts(message)``) and :meth:`drain`.

    ``on_connect`` (server side): started as a task with this stream once the transport is
    made; its failure is logged and the connection aborted. A connection attached late (after
    TLS is started on the server) gets what came before it, copied.
    """

    def __init__(
        self, conn: Connection | None = None, *, on_connect: OnConnect | None = None
    ) -> None:
        self._loop = asyncio.get_running_loop()
        self._conn = conn
        self._on_connect = on_connect
        self._owner_task: asyncio.Task[None] | None = None
        self._transport: asyncio.Transport | None = None
        self._fd = -1
        """The socket's descriptor, for :meth:`_write_gathered` (-1: none)."""
        self._switching = False
        """True while start_tls swaps the transport: reading is not switched then."""
        self._cursor = FrameCursor()
        self._gate = True
        """Read nothing until the owner has seen what was delivered (and has asked at all)."""
        self._paused_by_owner = False
        self._fresh = 0
        """Bytes delivered to the connection that no receive() has returned yet."""
        self._eof = False
        self._interrupted = False
        self._error: BaseException | None = None
        self._lost = False
        self._closed: asyncio.Future[None] = self._loop.create_future()
        self._waiter: asyncio.Future[None] | None = None
        self._write_paused = False
        self._drain_waiters: list[asyncio.Future[None]] = []
        self._view: memoryview | None = None
        self._direct = False
        """True when the latest get_buffer view is the connection's own body buffer."""
        self._body_is_direct = False
        """True while the rest of the current (large) body is read into its own buffer."""
        self._read_buffer: bytearray | None = None
        self._held: memoryview | None = None
        """A body's first bytes, read with its header, until the header has been seen."""
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
        how many (0: the peer closed its side, and the connection has been told;
        :data:`INTERRUPTED` after :meth:`interrupt`).

        Call it again only after ``next_event()`` returned ``NEED_DATA``: the stream reads a
        frame's body only once its header has been seen. Raises the OSError that broke the
        connection, once what arrived before it has been returned.
        """
        if self._waiter is not None:
            raise RuntimeError("receive() is already being awaited on this stream")
        while True:
            if self._interrupted:
                self._interrupted = False
                return INTERRUPTED
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

    def interrupt(self) -> None:
        """Make the pending :meth:`receive` (or the next one) return :data:`INTERRUPTED` at
        once: the owner has something else to look at (shutdown, a changed timeout). Costs
        nothing while the owner is not waiting; several calls before a receive count once."""
        self._interrupted = True
        self._wake()

    def pause_reading(self) -> None:
        """Read nothing more until :meth:`resume_reading` (TCP backpressure on the peer)."""
        self._paused_by_owner = True
        self._apply_reading()

    def resume_reading(self) -> None:
        self._paused_by_owner = False
        self._apply_reading()

    @property
    def write_paused(self) -> bool:
        """True while the transport holds more than its high-water mark: :meth:`drain`
        would wait."""
        return self._write_paused

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
        # bytes (a frame's head) are flat already; anything else is viewed as flat bytes.
        flat = (memoryview(p) if type(p) is bytes else blob_view(p) for p in parts)
        views = [view for view in flat if len(view)]
        if self.on_write is not None:
            for view in views:
                self.on_write(view)
        self.sent_bytes += sum(len(view) for view in views)
        if type(transport).writelines is asyncio.WriteTransport.writelines:
            self._write_gathered(transport, views)
        else:
            # uvloop's transports gather the parts in one writev; TLS keeps the views.
            transport.writelines(views)

    def _write_gathered(self, transport: asyncio.Transport, views: list[memoryview]) -> None:
        """Send ``views`` on asyncio's plain socket transport, whose ``writelines`` joins them
        into one bytes object (Python 3.11). When its buffer is empty, one ``writev`` sends
        the whole message from our buffers: one system call and one TCP segment train, not
        one per part (with TCP_NODELAY each part was a wake-up of the peer: a PONG cost two).
        What the kernel does not take goes through the transport, which copies it."""
        fd = self._fd
        if fd >= 0 and not transport.is_closing() and transport.get_write_buffer_size() == 0:
            try:
                sent = os.writev(fd, views[:IOV_MAX])
            except (BlockingIOError, InterruptedError):
                sent = 0
            except OSError:
                sent = 0  # the transport's own send meets the same error and reports it
            for index, view in enumerate(views):
                if sent >= len(view):
                    sent -= len(view)
                    continue
                views = [view[sent:], *views[index + 1 :]]
                break
            else:
                return
        for view in views:
            before = transport.get_write_buffer_size()
            transport.write(view)
            self.write_copied_bytes += max(transport.get_write_buffer_size() - before, 0)

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
        sock = transport.get_extra_info("socket")
        self._fd = sock.fileno() if sock is not None else -1
        # Nothing is read until the owner asks. Over TLS, not at once: asyncio's TLS layer
        # (3.11) sends the handshake's last message after connection_made, and only when
        # reading is not paused (a client that waits for the server would hang the handshake).
        if transport.get_extra_info("sslcontext") is not None:
            self._loop.call_soon(self._apply_reading)
        else:
            self._apply_reading()
        if self._on_connect is not None:
            self._owner_task = self._loop.create_task(self._run_owner(self._on_connect))

    def get_buffer(self, sizehint: int) -> memoryview:
        # Held bytes must reach the connection before anything is read after them (this
        # happens only when asyncio reads while we wait for the owner).
        self._release_held()
        body_left = self._cursor.body_left
        self._direct = self._body_is_direct and body_left > 0
        if self._direct and self._conn is not None:
            view = self._conn.get_buffer()[:body_left]
        else:
            if self._read_buffer is None:
                self._read_buffer = bytearray(READ_BUFFER_BYTES)
            view = memoryview(self._read_buffer)
        self._view = view
        return view

    def buffer_updated(self, nbytes: int) -> None:
        view, self._view = self._view, None
        if view is None or nbytes <= 0:
            return
        data = view[:nbytes]
        ready = self._cursor.advance(data)
        large_body = self._cursor.body_left > DIRECT_BODY_MIN
        conn = self._conn
        if conn is None:
            self._early += data
        elif self._direct:
            conn.buffer_updated(nbytes)
            self._body_is_direct = self._cursor.body_left > 0
        else:
            if not large_body:
                ready = nbytes
            self._body_is_direct = large_body
            conn.receive_data(data[:ready])
            if ready < nbytes:
                self._held = data[ready:]  # a view of our read buffer: nothing reads into it now
        self._fresh += nbytes
        self.received_bytes += nbytes
        if not self._direct and (large_body or self._fresh >= UNSEEN_BYTES_MAX):
            # A body comes next: its header must be admitted first. Or enough is unseen.
            self._gate = True
        self._apply_reading()
        if self._direct and self._body_is_direct:
            return  # the rest of a large body: the owner has nothing to do until it is whole
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
            # The owner has seen the header of the body these bytes start: they go into it.
            self._release_held()
            transport.resume_reading()

    def _release_held(self) -> None:
        held, self._held = self._held, None
        if held is not None and self._conn is not None:
            self._conn.receive_data(held)

    def _wake(self) -> None:
        if self._waiter is not None and not self._waiter.done():
            self._waiter.set_result(None)

    def _end_of_stream(self) -> None:
        if self._eof:
            return
        self._eof = True
        self._release_held()
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


__all__ = [
    "DIRECT_BODY_MIN",
    "INTERRUPTED",
    "READ_BUFFER_BYTES",
    "UNSEEN_BYTES_MAX",
    "OnConnect",
    "WireStream",
    "WriteObserver",
]
