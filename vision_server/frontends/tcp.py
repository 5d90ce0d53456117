"""The TCP front-end: the cellvision binary protocol (SPEC.md) over :mod:`wireio` streams, as a thin
adapter over :class:`vision_server.service.InspectionService`.

One task reads each connection and feeds a sans-IO :class:`protocol.Connection`; each INSPECT or
CAPTURE runs as a child task in the connection's TaskGroup and calls the service. What is this
front-end's own: the listener (``max_connections``, TLS started per connection, refusing with a
fatal BUSY), the handshake (versions, the token, the client's ``max_frame_bytes``), the
per-connection limits (``max_in_flight``) and timeouts (handshake, idle, frame: one watchdog
timer per connection; write), payload decoding (:mod:`.images`, run by the service: in a worker,
or for raw pixels of a cheap inspection on the event loop, ``inline_ms``) and the one table from
the service's errors to ERROR frames (:func:`error_frame`).

Admission happens when a frame's header arrives (:meth:`TcpSession._admit`): the service
reserves a worker slot and the bytes of a large body (:meth:`InspectionService.admit`) before the
body is read, so a refused request costs no read of its body. What a request holds is released
once its answer has been handed to the socket and drained.
"""

from __future__ import annotations

import asyncio
import contextlib
import hmac
import logging
import ssl
import time
from collections.abc import Coroutine
from typing import Any

from protocol import (
    NEED_DATA,
    PAUSED,
    AdmitLater,
    Busy,
    Capture,
    CellvisionError,
    Close,
    ConfigInvalid,
    Connection,
    ConnectionClosed,
    DeadlineExceeded,
    Error,
    Frames,
    Hello,
    ImageEncoding,
    ImagePayload,
    ImageRole,
    Inspect,
    Inspections,
    InternalError,
    InvalidArgument,
    Limits,
    ListInspections,
    LocalProtocolError,
    MalformedFrame,
    Message,
    NotAuthenticated,
    OperatorAnswer,
    OperatorCall,
    Ping,
    Pong,
    Reload,
    Reloaded,
    Result,
    Role,
    ShuttingDown,
    State,
    TooLargeToSend,
    UnexpectedMessage,
    UnsupportedVersion,
    Welcome,
    negotiate_version,
    payload_from_array,
)
from protocol.constants import SUPPORTED_VERSIONS, MessageType
from protocol.frames import Blob, Header
from wireio import INTERRUPTED, WireStream, serve

from ..config import DEFAULT_LINE_PORT, SERVER_VERSION, TcpSettings, welcome_limits
from ..results import ResultLogError
from ..service import (
    Admission,
    CaptureReply,
    CaptureRequest,
    FrameEncoding,
    InspectionService,
    InspectReply,
    InspectRequest,
    OperatorDesk,
    Refusal,
    Slot,
    Waiter,
    capture_key,
    deadline_after,
    desk_image,
    peer_name,
)
from .images import payload_loader

log = logging.getLogger("vision_server")

FRONTEND = "binary protocol"
"""This front-end's name at the service's front door (its counts, its refusals)."""
DEFAULT_MAX_FRAME_BYTES = Limits().max_frame_bytes
"""What a client accepts when its HELLO does not say (SPEC §3.4 default)."""
REFUSE_HELLO_TIMEOUT_S = 2.0
"""How long a refused connection may take to send its HELLO before it is closed anyway."""
CONNECTION_RETRY_AFTER_MS = 1000
"""The retry-after hint (ms) of the BUSY that refuses a connection over a connection limit
(SPEC §6.1): when another client leaves cannot be known, so this is a fixed pause, long
enough that a refused client does not spin on connect."""
CAPTURE_ENCODINGS: dict[str, FrameEncoding] = {"png": "png", "jpeg": "jpeg"}


def error_frame(exc: CellvisionError, request_id: int) -> Error:
    """The one table from the service's errors to this front-end's form: an ERROR frame with
    the error's code (SPEC §7), its message and details, for request ``request_id`` (0: the
    connection). Other front-ends map the same codes to an HTTP status, an error line or a
    Modbus exception."""
    return Error.from_exception(exc, request_id=request_id)


class TcpFrontend:
    """Listens for protocol clients and serves them with ``service``."""

    def __init__(self, service: InspectionService, settings: TcpSettings | None = None) -> None:
        self.service = service
        self.settings = settings or TcpSettings()
        self._refusing = 0
        self._server: asyncio.Server | None = None
        self._ssl: ssl.SSLContext | None = None
        self.connections: set[TcpSession] = set()
        """The sessions open now (counted towards ``max_connections``)."""
        self._stopping = asyncio.Event()
        self.operator_desk: OperatorDesk | None = None
        """Where OPERATOR_CALLs wait for a person (the console's); None: refused (SPEC §6.6)."""
        self.line_port: int | None = None
        """The line protocol's bound port when it is enabled: named to a peer that sends it
        text here (:meth:`explain`)."""

    def explain(self, exc: CellvisionError) -> CellvisionError:
        """``exc``, or for a bad magic that reads as text (a controller that sends the line
        protocol's ``T 1`` to this port) the same error saying which port this is."""
        if not (isinstance(exc, MalformedFrame) and exc.details.get("text")):
            return exc
        if self.line_port is not None:
            where = f"port {self.line_port}"
        else:
            where = f"its own port (line.port, default {DEFAULT_LINE_PORT}) when enabled"
        return MalformedFrame(
            f"this is the binary protocol's port; the line protocol listens on {where} "
            f"({exc.message})",
            request_id=exc.request_id,
            details=exc.details,
        )

    @property
    def started(self) -> bool:
        return self._server is not None

    @property
    def port(self) -> int:
        """The port actually bound (useful with port 0)."""
        return self.address[1]

    @property
    def address(self) -> tuple[str, int]:
        """The address and port actually bound."""
        if self._server is None or not self._server.sockets:
            raise RuntimeError("the server is not started")
        host, port = self._server.sockets[0].getsockname()[:2]
        return str(host), int(port)

    async def start(self) -> None:
        # TLS is started per connection in _accept, after the connection is counted, so that
        # connections still in the TLS handshake count towards max_connections and time out.
        self._ssl = self.settings.ssl_context()
        self._server = await serve(self._accept, self.settings.host, self.settings.port)
        log.info("listening on %s:%d", self.settings.host, self.port)

    async def stop(self) -> None:
        """Stop accepting; close every connection gracefully (SHUTTING_DOWN for what is still
        unanswered after the grace period)."""
        self._stopping.set()
        if self._server is not None:
            self._server.close()
        sessions = list(self.connections)
        for session in sessions:
            session.begin_shutdown()
        if sessions:
            await asyncio.wait(
                [asyncio.ensure_future(s.finished.wait()) for s in sessions],
                timeout=self.settings.shutdown_grace_s + 1.0,
            )
        if self._server is not None:
            await self._server.wait_closed()

    def health(self) -> dict[str, Any]:
        """The health report a PONG carries (SPEC §5.5): the service's, with this front-end's
        connections among the admission counters."""
        report = self.service.health()
        report["admission"] = {
            "connections": len(self.connections),
            "max_connections": self.settings.max_connections,
            **report["admission"],
        }
        return report

    def welcome_limits(self) -> dict[str, int]:
        return welcome_limits(self.settings, self.service.settings)

    # ------------------------------------------------------------------ connections

    async def _accept(self, stream: WireStream) -> None:
        peer = peer_name(stream.get_extra_info("peername"))
        admitted = (
            Refusal("stopping")
            if self._stopping.is_set()
            else self.service.door.enter(FRONTEND, peer, limit=self.settings.max_connections)
        )
        if isinstance(admitted, Refusal):
            reason = admitted.reason
            # Refusing politely costs a read (and a TLS handshake); never more of them at once
            # than connections: past that, a flood is just closed.
            if self._refusing >= self.settings.max_connections:
                stream.abort()
                return
            self._refusing += 1
            try:
                if await self._start_tls(stream, REFUSE_HELLO_TIMEOUT_S):
                    # A stopping server has no "later" to offer; a full one does.
                    retry = None if self._stopping.is_set() else CONNECTION_RETRY_AFTER_MS
                    await self._refuse(stream, reason, retry)
            finally:
                self._refusing -= 1
            return
        session = TcpSession(self, stream)
        self.connections.add(session)
        try:
            if await self._start_tls(stream, self.settings.handshake_timeout_s):
                await session.run()
        finally:
            self.connections.discard(session)
            session.admission_cleanup()
            admitted.leave()

    async def _start_tls(self, stream: WireStream, timeout_s: float) -> bool:
        """Wrap the connection in TLS when the server has TLS; False (and closed) on failure."""
        if self._ssl is None:
            return True
        try:
            await stream.start_tls(self._ssl, server_side=True, ssl_handshake_timeout=timeout_s)
        except Exception as exc:  # noqa: BLE001 - whatever the peer did, only it is dropped
            log.info("TLS handshake failed: %s", exc or type(exc).__name__)
            stream.abort()
            return False
        return True

    async def _refuse(self, stream: WireStream, reason: str, retry_after_ms: int | None) -> None:
        """Answer the HELLO with BUSY (with ``retry_after_ms`` in its details unless None),
        then close.

        The BUSY carries the HELLO's request id, so that the client's handshake fails with it,
        and ``fatal``, because the connection is closed after it (SPEC §7: the flag is
        authoritative). Reading the HELLO first also avoids closing with unread bytes, which
        would reset the connection before the client could read the BUSY.
        """
        conn = Connection(Role.SERVER, limits=self.settings.limits())
        stream.attach(conn)
        request_id = 0
        try:
            with contextlib.suppress(CellvisionError, TimeoutError):
                async with asyncio.timeout(REFUSE_HELLO_TIMEOUT_S):
                    event: object = NEED_DATA
                    while event is NEED_DATA:
                        await stream.receive()
                        event = conn.next_event()
                    if isinstance(event, Hello):
                        request_id = event.request_id
            exc = Busy(
                f"server refuses the connection: {reason}",
                request_id=request_id,
                fatal=True,
                details={} if retry_after_ms is None else {"retry_after_ms": retry_after_ms},
            )
            stream.writelines(_late_error(conn, exc))
            await stream.drain()
        except (ConnectionError, OSError) as exc:
            log.info("refused connection lost: %s", exc)
        finally:
            stream.close()


def _late_error(conn: Connection, exc: CellvisionError) -> list[Blob]:
    """The frame of an ERROR sent outside the normal flow (before HELLO, or after a fatal
    error), as buffers to write."""
    try:
        return conn.send_parts(Error.from_exception(exc))
    except LocalProtocolError:
        return Error.from_exception(exc).to_frame(conn.wire_version).serialize_parts()


class TcpSession:
    """One accepted connection.

    Every frame is admitted when its header arrives (:meth:`_admit`): the state machine, the
    connection's in-flight limit, a pool slot for INSPECT/CAPTURE and the bytes of a large body
    from the server's budget; a refused frame is answered (BUSY …) and its body skipped unread.
    What a request holds is released once its answer has been handed to the socket and drained.
    """

    def __init__(self, frontend: TcpFrontend, stream: WireStream) -> None:
        self.frontend = frontend
        self.service = frontend.service
        self.settings = frontend.settings
        self.stream = stream
        self.conn = Connection(
            Role.SERVER,
            limits=self.settings.limits(),
            versions=SUPPORTED_VERSIONS,
            check_header=self._check_header,
            admit=self._admit,
        )
        stream.attach(self.conn)
        self.finished = asyncio.Event()
        self.handshake_deadline = time.monotonic() + self.settings.handshake_timeout_s
        """The TLS handshake and HELLO must be done by then (monotonic seconds)."""
        self.max_in_flight = welcome_limits(self.settings, self.service.settings)["max_in_flight"]
        """What WELCOME announces (SPEC §6.1): requests beyond it are BUSY at their header, even
        when the server could make them wait."""
        self.max_reply_bytes = DEFAULT_MAX_FRAME_BYTES
        """The largest frame the client accepts (its HELLO's max_frame_bytes)."""
        self._shutdown = asyncio.Event()
        self._reading_over = asyncio.Event()
        """Set once nothing more is read: the client sent CLOSE or ended its stream."""
        self._tasks: set[asyncio.Task[None]] = set()
        self._frame_admission: Admission | None = None
        self._held: set[Admission] = set()
        # Admission that waits for a slot (see _admit and _wait_for_admission).
        self._waiter: Waiter | None = None
        self._granted: Slot | None = None
        self._refusal: CellvisionError | None = None
        self._last_activity = time.monotonic()
        self._frame_started: float | None = None
        self._watchdog: asyncio.TimerHandle | None = None
        """The read loop's one timer (:meth:`_watch`)."""
        peer = stream.get_extra_info("peername")
        self.peer = f"{peer[0]}:{peer[1]}" if isinstance(peer, tuple) else str(peer)

    def begin_shutdown(self) -> None:
        self._shutdown.set()
        self.stream.interrupt()

    # ------------------------------------------------------------------ admission

    def _check_header(self, header: Header) -> None:
        """Called by the connection with each header the state machine accepts, before any of
        the body: refuses (BUSY) what cannot be held whatever it asks for. Small frames are
        bounded per connection (one frame at a time); a larger body is only read when the
        service's byte budget can hold it, and its bytes are reserved now."""
        rid = header.request_id
        work = header.type in (MessageType.INSPECT, MessageType.CAPTURE)
        if work and len(self.conn.pending) >= self.max_in_flight:
            raise Busy(
                f"more than {self.max_in_flight} requests in flight on this connection",
                request_id=rid,
                details={"retry_after_ms": self.service.retry_after_ms(None)},
            )
        large = header.frame_length > self.conn.limits.max_handshake_frame_bytes
        if not (work or large):
            return  # a PING, a LIST_INSPECTIONS…: nothing to reserve
        try:
            admission = self.service.admit(
                work=False, body_bytes=header.frame_length if large else 0
            )
        except CellvisionError as exc:
            exc.request_id = rid  # the state machine answers it for this request
            raise
        self._hold_frame_admission(admission)

    def _admit(self, header: Header, metadata: dict[str, Any]) -> None:
        """Called by the connection once the frame's metadata has arrived, before its blobs
        (an image) are kept: an INSPECT or CAPTURE needs a worker slot in the lane its cost
        belongs to. Raises BUSY to refuse (the body is then skipped) or AdmitLater to stop
        reading this connection until a slot is free (:meth:`_wait_for_admission`)."""
        if header.type not in (MessageType.INSPECT, MessageType.CAPTURE):
            return
        held = self._frame_admission
        if held is None:  # a small body reserved nothing at its header
            held = self.service.admit(work=False)
            self._hold_frame_admission(held)
        if self._granted is not None:  # the slot this frame waited for
            slot = self._granted
            self._granted = None
            held.hold_slot(slot)
            return
        if self._refusal is not None:  # its wait ended without a slot
            refusal, self._refusal = self._refusal, None
            refusal.request_id = header.request_id
            raise refusal
        admitted = self.service.pool.reserve_or_wait(_cost_key(header, metadata))
        if isinstance(admitted, Waiter):
            self._waiter = admitted
            raise AdmitLater
        held.hold_slot(admitted)

    def _hold_frame_admission(self, admission: Admission) -> None:
        self._frame_admission = admission
        self._held.add(admission)

    async def _wait_for_admission(self) -> None:
        """The next frame waits for a worker slot: nothing more is read from this connection
        meanwhile (the client's sends block: TCP backpressure). Ends with the slot, or with
        BUSY after ``admission_wait_s``, or SHUTTING_DOWN; the frame is then asked again."""
        waiter, self._waiter = self._waiter, None
        assert waiter is not None
        waiting = asyncio.ensure_future(self.service.slot_after(waiter))
        stop = asyncio.ensure_future(self._shutdown.wait())
        self.stream.pause_reading()
        try:
            await asyncio.wait({waiting, stop}, return_when=asyncio.FIRST_COMPLETED)
        finally:
            self.stream.resume_reading()
            stop.cancel()
            if not waiting.done():
                waiting.cancel()
                with contextlib.suppress(asyncio.CancelledError):
                    await waiting
        if waiting.cancelled():
            self._refusal = ShuttingDown("the server is stopping")
            return
        exc = waiting.exception()
        if exc is None:
            self._granted = waiting.result()
        elif isinstance(exc, CellvisionError):
            self._refusal = exc
        else:
            raise exc
        # The frame timeout is about the sender's speed: the wait was ours.
        self._frame_started = time.monotonic()

    def _take_frame_admission(self) -> Admission | None:
        admission, self._frame_admission = self._frame_admission, None
        return admission

    def _release(self, admission: Admission | None) -> None:
        if admission is not None:
            admission.release()
            self._held.discard(admission)

    def admission_cleanup(self) -> None:
        """Give back everything this connection still holds (it is gone)."""
        if self._granted is not None:
            self.service.pool.release(self._granted)
            self._granted = None
        for admission in list(self._held):
            self._release(admission)
        self._frame_admission = None

    # ------------------------------------------------------------------ the connection

    async def run(self) -> None:
        try:
            async with asyncio.TaskGroup() as group:
                graceful = await self._read_loop(group)
                self._reading_over.set()  # an operator call's robot is no longer listening
                if not graceful:
                    for task in list(self._tasks):
                        task.cancel()
                # Graceful: everything in flight is answered before CLOSE.
            if self.conn.state is not State.CLOSED:
                self._write(Close(reason="closing"))
                await self._drain()
        # except*: a request task's failure reaches here wrapped in the TaskGroup's
        # ExceptionGroup, and a peer that resets the connection is no server error.
        except* (ConnectionError, OSError) as lost:
            log.info("%s: connection lost: %s", self.peer, lost.exceptions[0])
        except* Exception:
            log.exception("%s: unexpected error; closing this connection only", self.peer)
        finally:
            if self._watchdog is not None:
                self._watchdog.cancel()
                self._watchdog = None
            self.stream.close()
            with contextlib.suppress(Exception):
                await self.stream.wait_closed()
            self.admission_cleanup()
            self.finished.set()

    def _read_timeout(self) -> tuple[float | None, str]:
        """Seconds until the connection has been silent too long, and what it then says."""
        settings = self.settings
        now = time.monotonic()
        if self.conn.state in (State.HANDSHAKE, State.HELLO_RECEIVED):
            limit = settings.handshake_timeout_s
            return max(self.handshake_deadline - now, 0.0), f"no HELLO within {limit:g} s"
        if self._frame_started is not None:
            limit = settings.frame_timeout_s
            return (
                max(self._frame_started + limit - now, 0.0),
                f"a frame was not complete within {limit:g} s",
            )
        if not self.conn.pending and not self._tasks:
            limit = settings.idle_timeout_s
            return (
                max(self._last_activity + limit - now, 0.0),
                f"idle for {limit:g} s (send PING to keep a connection open)",
            )
        return None, ""

    def _watch(self, timeout: float | None) -> None:
        """Have the watchdog look again within ``timeout`` seconds (None: nothing is due).
        One timer per connection, moved only when a deadline comes nearer than it: each read
        of a large body would otherwise make and cancel a timer of its own."""
        if timeout is None:
            return  # an armed watchdog finds nothing due and stops
        loop = asyncio.get_running_loop()
        due = loop.time() + timeout
        watchdog = self._watchdog
        if watchdog is not None and watchdog.when() <= due:
            return
        if watchdog is not None:
            watchdog.cancel()
        self._watchdog = loop.call_at(due, self._watchdog_due)

    def _watchdog_due(self) -> None:
        self._watchdog = None
        timeout, _ = self._read_timeout()
        if timeout is None:
            return
        if timeout <= 0.0:
            self.stream.interrupt()  # the read loop finds the timeout due and closes
        else:
            self._watch(timeout)  # the deadline moved on (activity): look again then

    async def _read_loop(self, group: asyncio.TaskGroup) -> bool:
        """Read and dispatch until the peer closes (True) or broke the protocol (False)."""
        while True:
            # Backpressure: do not read more while the peer is not reading our answers.
            await self._drain()
            if self._shutdown.is_set():
                await self._shutdown_session()
                return True
            # One wait per read, woken by the peer's bytes or interrupt(): on shutdown, and by
            # the watchdog once a timeout is due (the idle timeout is set when the last request
            # is answered, so a client that goes silent after its answers is closed after
            # idle_timeout_s).
            timeout, why = self._read_timeout()
            if timeout is not None and timeout <= 0.0:
                log.info("%s: %s; closing", self.peer, why)
                self._write(Close(reason=why))
                await self._drain()
                return False
            self._watch(timeout)
            got = await self.stream.receive()
            if got == INTERRUPTED:
                continue
            # The bytes are in the connection already (read into its frame body).
            if got and self._frame_started is None:
                self._frame_started = time.monotonic()
            frame_ended = False
            while True:
                try:
                    event = self.conn.next_event()
                except CellvisionError as refused:
                    frame_ended = True
                    self._release(self._take_frame_admission())
                    exc = self.frontend.explain(refused)
                    log.info("%s: %s: %s", self.peer, exc.code.name, exc.message)
                    if exc.fatal:
                        self.stream.writelines(_late_error(self.conn, exc))
                        await self._drain()
                        return False
                    # Request id 0 (e.g. a request sent with id 0) gets a connection-level
                    # ERROR: SPEC §6.1 and §7 want an answer even then.
                    self._write(Error.from_exception(exc))
                    continue
                if event is NEED_DATA:
                    break
                if event is PAUSED:
                    await self._wait_for_admission()
                    continue
                frame_ended = True
                if isinstance(event, ConnectionClosed):
                    return True
                assert isinstance(event, Message)
                # The whole frame is in: a request's deadline counts from now (SPEC §6.1).
                arrived = self._last_activity = time.monotonic()
                if isinstance(event, Hello) and not self._token_ok(event):
                    # The front door slows down guessing: the refusal waits, doubling per
                    # failure from this host (nothing else is read meanwhile).
                    await asyncio.sleep(self.service.door.auth_failed(self.peer))
                admission = self._take_frame_admission()
                try:
                    keep_going = self._dispatch(event, group, admission, arrived)
                except BaseException:
                    self._release(admission)
                    raise
                if not keep_going:
                    return self.conn.state is not State.CLOSED
            # The frame timeout counts from a frame's first byte: bytes that trickle in keep
            # the same start (a slow sender must not hold the connection by dribbling), a new
            # frame begun in this chunk starts now.
            if not self.conn.receiving_frame:
                self._frame_started = None
            elif frame_ended:
                self._frame_started = time.monotonic()

    def _dispatch(
        self,
        message: Message,
        group: asyncio.TaskGroup,
        admission: Admission | None,
        arrived: float,
    ) -> bool:
        """Answer or start one request (``arrived``: when its frame was complete, monotonic
        seconds); False when the connection is to close. A request task takes over
        ``admission``; for everything else it is released here."""
        if isinstance(message, Inspect | Capture):
            self._start(group, self._answer(message, admission, arrived))
            return True
        self._release(admission)
        if isinstance(message, Hello):
            return self._handshake(message)
        if isinstance(message, Ping):
            self._write(Pong(message.request_id, message.data, self.frontend.health()))
            return True
        if isinstance(message, ListInspections):
            self._write(
                Inspections(message.request_id, self.service.catalog.inspection_descriptors())
            )
            return True
        if isinstance(message, Close):
            return False  # the TaskGroup finishes what is in flight, then CLOSE goes out
        if isinstance(message, Error):  # the client's fatal ERROR (SPEC §7): it is over
            log.info("%s: the client ended the connection: %s", self.peer, message.message)
            return False
        if isinstance(message, Reload):
            self._start(group, self._reload(message))
            return True
        if isinstance(message, OperatorCall):
            self._start(group, self._operator_call(message, arrived))
            return True
        self._write(
            Error.from_exception(
                UnexpectedMessage(
                    f"{message.TYPE.name} is not handled by this server",
                    request_id=message.request_id,
                )
            )
        )
        return True

    def _start(self, group: asyncio.TaskGroup, work: Coroutine[Any, Any, None]) -> None:
        task = group.create_task(work)
        self._tasks.add(task)
        task.add_done_callback(self._task_done)

    def _task_done(self, task: asyncio.Task[None]) -> None:
        self._tasks.discard(task)
        if not self._tasks:
            # The idle timeout starts now: the watchdog is set for it without waking the
            # read loop (it finds the timeout due, or moved on by a new request, then).
            self._watch(self._read_timeout()[0])

    def _token_ok(self, hello: Hello) -> bool:
        """Whether the HELLO carries the server's token, when it has one (constant-time)."""
        expected = self.settings.auth_token
        if expected is None:
            return True
        return hmac.compare_digest((hello.auth_token or "").encode(), expected.encode())

    def _handshake(self, hello: Hello) -> bool:
        version = negotiate_version(hello.versions, self.conn.versions)
        if version is None:
            offered = ", ".join(f"{a}.{b}" for a, b in hello.versions)
            exc: CellvisionError = UnsupportedVersion(
                f"no common major version: client offers {offered}, server speaks "
                + ", ".join(f"{a}.{b}" for a, b in self.conn.versions),
                request_id=hello.request_id,
                details={"supported": [list(v) for v in self.conn.versions]},
            )
            self._write(Error.from_exception(exc))
            return False
        if not self._token_ok(hello):
            self._write(
                Error.from_exception(
                    NotAuthenticated(
                        "missing or wrong auth_token in HELLO", request_id=hello.request_id
                    )
                )
            )
            return False
        # Each HELLO is a new attempt (SPEC §5.4): its limit, or the default, replaces that of
        # an earlier HELLO refused because its WELCOME would not fit.
        self.max_reply_bytes = (
            DEFAULT_MAX_FRAME_BYTES if hello.max_frame_bytes is None else hello.max_frame_bytes
        )
        settings = self.settings
        catalog = self.service.catalog
        self._write(
            Welcome(
                hello.request_id,
                version,
                settings.name,
                SERVER_VERSION,
                self.frontend.welcome_limits(),
                catalog.inspection_descriptors(),
                catalog.camera_descriptors(),
            )
        )
        log.info("%s: handshake done (version %d.%d, client %r)", self.peer, *version, hello.client)
        return True

    async def _answer(
        self, request: Inspect | Capture, admission: Admission | None, arrived: float
    ) -> None:
        rid = request.request_id
        try:
            response = await self._response(request, admission, arrived)
            if rid in self.conn.pending:
                self._write(response)
                # What the socket did not take is the transport's now (a copy, or its own
                # reference): the answer's arrays and PNG need not live on while a slow
                # reader drains, which the byte budget counts once.
                del response
                await self._drain()
        finally:
            # The reply is in the socket (or the connection is gone): its memory is free.
            self._release(admission)

    async def _response(
        self, request: Inspect | Capture, admission: Admission | None, arrived: float
    ) -> Message:
        """The answer to ``request``: RESULT, FRAMES or ERROR. The service's reply (with the
        overlay's pixels beside its PNG) ends here; only the message goes on."""
        rid = request.request_id
        try:
            if isinstance(request, Inspect):
                reply = await self.service.inspect(
                    self._inspect_request(request, arrived), admission=admission
                )
                return result_message(rid, reply)
            wanted = _capture_request(request, arrived, self.max_reply_bytes)
            captured = await self.service.capture(wanted, admission=admission)
            return _frames(rid, captured, wanted.encoding)
        except CellvisionError as exc:
            return error_frame(exc, rid)
        except Exception as exc:  # a bug in an inspection must not take the server down
            log.exception("%s: request %d failed", self.peer, rid)
            return error_frame(InternalError(f"{type(exc).__name__}: {exc}"), rid)

    def _inspect_request(self, message: Inspect, arrived: float) -> InspectRequest:
        return InspectRequest(
            message.inspection,
            payload_loader(message.images) if message.images else None,
            overlay=".png" if message.overlay else None,
            options=message.options,
            arrived=arrived,
            deadline=deadline_after(arrived, message.deadline_ms),
            peer=self.peer,
            request_id=message.request_id,
        )

    async def _reload(self, request: Reload) -> None:
        rid = request.request_id
        response: Message
        if not self.settings.allow_reload or self.service.reloader is None:
            why = (
                "this server was started without a configuration file"
                if self.service.reloader is None
                else "reload is disabled (allow_reload: false)"
            )
            response = error_frame(InvalidArgument(why), rid)
        else:
            try:
                catalog = await self.service.reload()
            except CellvisionError as exc:
                if isinstance(exc, ConfigInvalid):
                    log.error(
                        "%s: reload refused, the old configuration stays: %s",
                        self.peer,
                        exc.message,
                    )
                response = error_frame(exc, rid)
            else:
                response = Reloaded(
                    rid,
                    catalog.config_hash,
                    catalog.inspection_descriptors(),
                    catalog.camera_descriptors(),
                    catalog.notes,
                )
        if rid in self.conn.pending:
            self._write(response)
            await self._drain()

    async def _operator_call(self, call: OperatorCall, arrived: float) -> None:
        """Post the call on the operator desk and answer with the person's choice (SPEC §6.6):
        no worker slot, just a wait, ended by the answer, the deadline, the client leaving
        (DEADLINE_EXCEEDED: it gave up) or shutdown."""
        rid = call.request_id
        desk = self.frontend.operator_desk
        response: Message
        try:
            if desk is None:
                raise UnexpectedMessage(
                    "this server has no operator console (console.enabled: false): nobody "
                    "could answer an OPERATOR_CALL; ask the operator another way",
                    request_id=rid,
                )
            if len(self.conn.pending) > self.settings.max_in_flight:
                raise Busy(
                    f"more than {self.settings.max_in_flight} requests in flight",
                    details={"retry_after_ms": self.service.retry_after_ms(None)},
                )
            max_pixels = self.service.settings.max_image_pixels
            images = await asyncio.to_thread(
                lambda: [
                    desk_image(p, max_pixels=max_pixels, where=f"images[{i}]")
                    for i, p in enumerate(call.images)
                ]
            )
            timeout_s = None
            if call.deadline_ms is not None:
                timeout_s = max(arrived + call.deadline_ms / 1000.0 - time.monotonic(), 0.0)
            await self._check_result_id(call)
            posted = desk.post(
                peer=self.peer,
                message=call.message,
                choices=call.choices,
                inspection=call.inspection,
                skill=call.skill,
                images=images,
                timeout_s=timeout_s,
                result_id=call.result_id,
            )
            answer = await desk.wait(
                posted,
                timeout_s=timeout_s,
                stop_when={
                    self._shutdown: ShuttingDown("the server is stopping"),
                    self._reading_over: DeadlineExceeded(
                        "the client closed its connection; the operator call was withdrawn"
                    ),
                },
            )
            response = OperatorAnswer(
                rid, answer.choice, answer.by, answer.answered_at, answer.reason, answer.operator
            )
        except CellvisionError as exc:
            response = error_frame(exc, rid)
        if rid in self.conn.pending:
            self._write(response)
            await self._drain()

    async def _check_result_id(self, call: OperatorCall) -> None:
        """An OPERATOR_CALL's ``result_id`` must name a row of the result log (its answer is
        written there): INVALID_ARGUMENT otherwise. A log that cannot be read now (a database
        that is down) is given the benefit of the doubt; the annotation is tried on answer."""
        results = self.service.results
        if call.result_id is None or results is None:
            return
        try:
            row = await asyncio.to_thread(results.get, call.result_id)
        except ResultLogError:
            return
        if row is None:
            raise InvalidArgument(
                f"result_id {call.result_id} is no result of this server's result log",
                request_id=call.request_id,
                details={"option": "result_id"},
            )

    async def _shutdown_session(self) -> None:
        grace = self.settings.shutdown_grace_s
        if self._tasks:
            await asyncio.wait(set(self._tasks), timeout=grace)
        for task in list(self._tasks):
            task.cancel()
        for request_id in sorted(self.conn.pending):
            self._write(
                Error.from_exception(ShuttingDown("the server is stopping", request_id=request_id))
            )
        if self.conn.state is State.OPEN:
            self._write(Close(reason="server shutting down"))
        await self._drain()

    def _write(self, message: Message) -> None:
        """Send ``message``. An answer the client could not receive (larger than its HELLO's
        max_frame_bytes) or cannot be encoded is replaced by an ERROR for its request."""
        try:
            data = self._encode(message)
        except LocalProtocolError:
            log.warning(
                "%s: dropped %s that the state machine refused", self.peer, message.TYPE.name
            )
            return
        if not self.stream.is_closing():
            self.stream.writelines(data)
            self._last_activity = time.monotonic()

    def _encode(self, message: Message) -> list[Blob]:
        rid = message.request_id
        limit = None if isinstance(message, Error) else self.max_reply_bytes
        try:
            return self.conn.send_parts(message, max_bytes=limit)
        except (TypeError, ValueError) as exc:
            # Data JSON cannot carry (numpy scalars, NaN): fail this request, not the
            # connection (the state machine is unchanged when serializing fails).
            log.error("%s: answer to request %d not sendable: %s", self.peer, rid, exc)
            return self.conn.send_parts(
                Error.from_exception(
                    InternalError(f"the server could not encode its answer: {exc}", request_id=rid)
                )
            )
        except TooLargeToSend as big:
            log.warning(
                "%s: %s of %d bytes exceeds the client's limit",
                self.peer,
                message.TYPE.name,
                big.size,
            )
            return self.conn.send_parts(
                Error.from_exception(
                    InvalidArgument(
                        f"the answer ({message.TYPE.name}) is {big.size} bytes, more than the "
                        f"{big.max_size} bytes the client accepts (HELLO max_frame_bytes); ask "
                        "for less (fewer frames, a compressed encoding, no overlay)",
                        request_id=rid,
                        details={"size": big.size, "max_size": big.max_size},
                    )
                )
            )

    async def _drain(self) -> None:
        """Wait until the client has taken our answers; drop a client that does not read."""
        if self.stream.is_closing() or not self.stream.write_paused:
            return  # nothing to wait for: no timer either
        try:
            async with asyncio.timeout(self.settings.write_timeout_s):
                await self.stream.drain()
        except TimeoutError:
            log.warning(
                "%s: the client has not read its answers for %g s; dropping it",
                self.peer,
                self.settings.write_timeout_s,
            )
            self.stream.abort()
            raise ConnectionAbortedError("slow reader dropped") from None


def result_message(request_id: int, reply: InspectReply) -> Result:
    """The RESULT for ``reply`` (SPEC §6.3): the overlay as the PNG the service encoded."""
    images: tuple[ImagePayload, ...] = ()
    overlay = reply.overlay
    if overlay is not None and overlay.encoded is not None:
        height, width = overlay.image.shape[:2]
        images = (
            ImagePayload(ImageEncoding.PNG, width, height, overlay.encoded, ImageRole.OVERLAY),
        )
    return Result(
        request_id,
        reply.inspection,
        reply.passed,
        reply.data,
        reply.timing,
        reply.camera,
        reply.config_hash,
        images,
        reply.stored,
        reply.result_id,
    )


def _cost_key(header: Header, metadata: dict[str, Any]) -> str | None:
    """What the service's cost model knows a request by: the inspection's name for INSPECT,
    the camera for CAPTURE (None when the metadata does not say; the request will fail on
    its own once read)."""
    if header.type == MessageType.INSPECT:
        name = metadata.get("inspection")
        return name if isinstance(name, str) else None
    camera = metadata.get("camera")
    return capture_key(camera) if isinstance(camera, str) else None


def _capture_request(message: Capture, arrived: float, max_reply_bytes: int) -> CaptureRequest:
    encoding = None
    if message.encoding is not None:
        encoding = CAPTURE_ENCODINGS.get(message.encoding)
        if encoding is None:
            raise InvalidArgument(
                f"encoding {message.encoding!r}: CAPTURE takes 'png' or 'jpeg' "
                "(or nothing, for raw frames)"
            )
    return CaptureRequest(
        message.camera,
        message.count,
        message.depth,
        encoding,
        max_reply_bytes,
        arrived=arrived,
        deadline=deadline_after(arrived, message.deadline_ms),
    )


def _frames(request_id: int, reply: CaptureReply, encoding: FrameEncoding | None) -> Frames:
    payloads: list[ImagePayload] = []
    for frame in reply.frames:
        if frame.encoded is not None:
            height, width = frame.color.shape[:2]
            wire = ImageEncoding.PNG if encoding == "png" else ImageEncoding.JPEG
            payloads.append(ImagePayload(wire, width, height, frame.encoded))
        else:
            payloads.append(payload_from_array(frame.color))
        if frame.depth is not None:
            payloads.append(payload_from_array(frame.depth, role=ImageRole.DEPTH))
    stamps = tuple(f.timestamp for f in reply.frames)
    return Frames(request_id, reply.camera, tuple(payloads), stamps, reply.intrinsics)


__all__ = ["TcpFrontend", "TcpSession", "error_frame", "result_message"]
