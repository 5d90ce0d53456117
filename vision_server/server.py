"""The asyncio adapter around the sans-IO protocol: accept connections, answer requests.

One task reads each connection and feeds a :class:`protocol.Connection`; each INSPECT or
CAPTURE runs as a child task in the connection's TaskGroup, its CPU work in a bounded thread
pool (OpenCV releases the GIL). Admission is bounded: beyond the pool's workers plus
``queue_depth`` waiting jobs, or beyond ``max_in_flight`` requests on one connection, a request
is answered BUSY at once instead of queueing.
"""

from __future__ import annotations

import asyncio
import contextlib
import hmac
import logging
import os
import ssl
import threading
import time
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from typing import Any, TypeVar

from protocol import (
    DEFAULT_PORT,
    NEED_DATA,
    BadImage,
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
    Message,
    NotAuthenticated,
    Ping,
    Pong,
    Reload,
    Reloaded,
    Result,
    Role,
    ShuttingDown,
    State,
    UnexpectedMessage,
    UnsupportedVersion,
    Welcome,
    array_from_payload,
    negotiate_version,
    payload_from_array,
)
from protocol.constants import SUPPORTED_VERSIONS

from .cameras import Camera, CameraFrame
from .catalog import Catalog, Image, InspectionInput, InspectionOutcome
from .results import ResultEntry, ResultLog

__version__ = "0.1.0"
log = logging.getLogger("vision_server")
_T = TypeVar("_T")

READ_CHUNK = 256 * 1024
MAX_CAPTURE_FRAMES = 64
REFUSE_HELLO_TIMEOUT_S = 2.0
"""How long a refused connection may take to send its HELLO before it is closed anyway."""


@dataclass(frozen=True)
class ServerSettings:
    """How the server listens and what it accepts. Sizes in bytes, durations in seconds."""

    host: str = "127.0.0.1"
    port: int = DEFAULT_PORT
    name: str = "cellvision"
    max_frame_bytes: int = 64 * 1024 * 1024
    max_image_pixels: int = 4096 * 4096
    max_in_flight: int = 32
    """Requests one connection may have in flight; more are answered BUSY."""
    max_connections: int = 64
    workers: int = field(default_factory=lambda: os.cpu_count() or 2)
    """Threads for CPU-bound inspection work."""
    queue_depth: int = 16
    """Jobs that may wait for a worker; beyond workers + queue_depth a request gets BUSY."""
    auth_token: str | None = None
    shutdown_grace_s: float = 5.0
    tls_cert: str | None = None
    tls_key: str | None = None
    capture_timeout_s: float = 5.0
    """How long a server camera may take for the frames of one request (without a deadline)."""
    allow_reload: bool = True
    """Whether a client may ask for a configuration reload (RELOAD)."""
    handshake_timeout_s: float = 10.0
    """How long a new connection may take to complete its HELLO; then it is closed, so that
    silent connections cannot hold every one of the ``max_connections`` slots."""

    def limits(self) -> Limits:
        return Limits(max_frame_bytes=self.max_frame_bytes, max_image_pixels=self.max_image_pixels)

    def ssl_context(self) -> ssl.SSLContext | None:
        if not self.tls_cert:
            return None
        context = ssl.create_default_context(ssl.Purpose.CLIENT_AUTH)
        context.load_cert_chain(self.tls_cert, self.tls_key)
        return context


class WorkPool:
    """A thread pool with bounded admission: ``try_submit`` refuses instead of queueing."""

    def __init__(self, workers: int, queue_depth: int) -> None:
        self.capacity = workers + queue_depth
        self._executor = ThreadPoolExecutor(max_workers=workers, thread_name_prefix="inspect")
        self._lock = threading.Lock()
        self._admitted = 0

    @property
    def admitted(self) -> int:
        return self._admitted

    def try_submit(self, fn: Callable[[], _T]) -> asyncio.Future[_T] | None:
        """Run ``fn`` in the pool; None when the pool is full. The slot is held until ``fn``
        returns, even if the awaiting request gave up (its deadline passed)."""
        with self._lock:
            if self._admitted >= self.capacity:
                return None
            self._admitted += 1

        def job() -> _T:
            try:
                return fn()
            finally:
                with self._lock:
                    self._admitted -= 1

        return asyncio.get_running_loop().run_in_executor(self._executor, job)

    def shutdown(self) -> None:
        self._executor.shutdown(wait=False, cancel_futures=True)


class VisionServer:
    """A cellvision server. Use ``async with VisionServer(...) as server`` or start()/stop().

    ``catalog`` is swapped whole by :meth:`replace_catalog` (configuration reload) while
    connections stay open.
    """

    def __init__(
        self,
        catalog: Catalog,
        settings: ServerSettings | None = None,
        *,
        results: ResultLog | None = None,
        reloader: Callable[[], Catalog] | None = None,
    ) -> None:
        self.settings = settings or ServerSettings()
        self.catalog = catalog
        self.results = results
        self.reloader = reloader
        """Builds the catalog of a re-read configuration (raises ConfigError when invalid)."""
        self._pool = WorkPool(self.settings.workers, self.settings.queue_depth)
        self._server: asyncio.Server | None = None
        self._connections: set[_ClientSession] = set()
        self._stopping = asyncio.Event()
        self.on_result: Callable[[ResultRecord], None] | None = None

    # ------------------------------------------------------------------ lifecycle

    @property
    def port(self) -> int:
        """The port actually bound (useful with port 0)."""
        if self._server is None or not self._server.sockets:
            raise RuntimeError("the server is not started")
        return int(self._server.sockets[0].getsockname()[1])

    async def start(self) -> None:
        self._server = await asyncio.start_server(
            self._accept,
            self.settings.host,
            self.settings.port,
            ssl=self.settings.ssl_context(),
            limit=READ_CHUNK,
        )
        log.info("listening on %s:%d", self.settings.host, self.port)

    async def serve_forever(self) -> None:
        if self._server is None:
            await self.start()
        await self._stopping.wait()

    async def stop(self) -> None:
        """Stop accepting; close every connection gracefully (SHUTTING_DOWN for what is still
        unanswered after the grace period), then stop the pool."""
        self._stopping.set()
        if self._server is not None:
            self._server.close()
        sessions = list(self._connections)
        for session in sessions:
            session.begin_shutdown()
        if sessions:
            await asyncio.wait(
                [asyncio.ensure_future(s.finished.wait()) for s in sessions],
                timeout=self.settings.shutdown_grace_s + 1.0,
            )
        if self._server is not None:
            await self._server.wait_closed()
        self._pool.shutdown()

    async def __aenter__(self) -> VisionServer:
        await self.start()
        return self

    async def __aexit__(self, *exc: object) -> None:
        await self.stop()

    def replace_catalog(self, catalog: Catalog) -> None:
        """Serve new requests with ``catalog``; requests already running finish on the old,
        whose lease they hold (retiring it is its owner's job, see CellRuntime.reload)."""
        self.catalog = catalog

    # ------------------------------------------------------------------ connections

    async def _accept(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        if len(self._connections) >= self.settings.max_connections or self._stopping.is_set():
            reason = "too many connections" if not self._stopping.is_set() else "stopping"
            await self._refuse(reader, writer, reason)
            return
        session = _ClientSession(self, reader, writer)
        self._connections.add(session)
        try:
            await session.run()
        finally:
            self._connections.discard(session)

    async def _refuse(
        self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter, reason: str
    ) -> None:
        """Answer the HELLO with BUSY, then close.

        The BUSY carries the HELLO's request id, so that the client's handshake fails with it,
        and ``fatal``, because the connection is closed after it (SPEC §7: the flag is
        authoritative). Reading the HELLO first also avoids closing with unread bytes, which
        would reset the connection before the client could read the BUSY.
        """
        conn = Connection(Role.SERVER, limits=self.settings.limits())
        request_id = 0
        try:
            with contextlib.suppress(CellvisionError, TimeoutError):
                async with asyncio.timeout(REFUSE_HELLO_TIMEOUT_S):
                    event: object = NEED_DATA
                    while event is NEED_DATA:
                        conn.receive_data(await reader.read(READ_CHUNK))
                        event = conn.next_event()
                    if isinstance(event, Hello):
                        request_id = event.request_id
            exc = Busy(
                f"server refuses the connection: {reason}", request_id=request_id, fatal=True
            )
            writer.write(_late_error(conn, exc))
            await writer.drain()
        except (ConnectionError, OSError) as exc:
            log.info("refused connection lost: %s", exc)
        finally:
            writer.close()

    # ------------------------------------------------------------------ request work

    async def run_inspection(self, request: Inspect, *, peer: str = "") -> Result:
        """Get the images (from the request or the camera), run the named inspection in the
        pool, record it in the result log, build the RESULT."""
        # The lease keeps the catalog's cameras open until this request is done with them.
        with self.catalog.lease_newest() as lease:
            return await self._run_inspection(request, lease.catalog, peer)

    async def _run_inspection(self, request: Inspect, catalog: Catalog, peer: str) -> Result:
        started = time.perf_counter()
        rid = request.request_id
        inspection = catalog.inspection(request.inspection, request_id=rid)
        camera = catalog.camera(inspection.camera, request_id=rid)
        acquire: Callable[[], InspectionInput]
        if camera.source == "request":
            if not request.images:
                raise BadImage(
                    f"inspection {inspection.name!r} uses camera {camera.name!r}, whose images "
                    "arrive in the request, and the request has none",
                    request_id=rid,
                )

            def acquire() -> InspectionInput:
                decoded = _decode_input(
                    request.images,
                    rid,
                    inspection.uses_depth,
                    inspection.name,
                    self.settings.max_image_pixels,
                )
                return InspectionInput(decoded.color, decoded.depth, camera.intrinsics)

        else:
            if request.images:
                raise InvalidArgument(
                    f"inspection {inspection.name!r} takes its images from the server camera "
                    f"{camera.name!r}; the request must not carry images",
                    request_id=rid,
                )
            timeout_s = self._capture_timeout(request.deadline_ms)

            def acquire() -> InspectionInput:
                frames = _grab(camera, inspection.frames, timeout_s, rid)
                depth = tuple(f.depth for f in frames if f.depth is not None)
                return InspectionInput(
                    frames[0].color, depth if inspection.uses_depth else (), camera.intrinsics
                )

        def work() -> tuple[InspectionOutcome, float, tuple[ImagePayload, ...]]:
            image = acquire()
            t0 = time.perf_counter()
            try:
                outcome = inspection.run(image, overlay=request.overlay)
            except CellvisionError as exc:
                exc.request_id = rid
                self._record(
                    inspection.name,
                    camera.name,
                    False,
                    {},
                    t0,
                    catalog,
                    rid,
                    peer,
                    image.color,
                    error=f"{exc.code.name}: {exc.message}",
                )
                raise
            compute_ms = (time.perf_counter() - t0) * 1000.0
            self._record(
                inspection.name,
                camera.name,
                outcome.passed,
                outcome.data,
                t0,
                catalog,
                rid,
                peer,
                image.color,
            )
            images: tuple[ImagePayload, ...] = ()
            if request.overlay and outcome.overlay is not None:
                # PNG encoding is CPU work too: here, not on the event loop of every connection.
                images = (
                    payload_from_array(
                        outcome.overlay, role=ImageRole.OVERLAY, encoding=ImageEncoding.PNG
                    ),
                )
            return outcome, compute_ms, images

        outcome, compute_ms, images = await self._in_pool(
            work, rid, request.deadline_ms, hold=catalog
        )
        total_ms = (time.perf_counter() - started) * 1000.0
        result = Result(
            rid,
            inspection.name,
            outcome.passed,
            outcome.data,
            {"compute_ms": round(compute_ms, 3), "total_ms": round(total_ms, 3)},
            camera.name,
            catalog.config_hash,
            images,
        )
        if self.on_result is not None:
            self.on_result(ResultRecord(result, request, compute_ms))
        return result

    def _record(
        self,
        inspection: str,
        camera: str,
        passed: bool,
        data: dict[str, Any],
        t0: float,
        catalog: Catalog,
        request_id: int,
        peer: str,
        image: Image,
        *,
        error: str | None = None,
    ) -> None:
        """Log one run before its answer is sent, so that an acknowledged result is on disk.
        The log never raises: a full disk is counted and logged, the answer still goes out."""
        if self.results is None:
            return
        self.results.record(
            ResultEntry(
                time=time.time(),
                inspection=inspection,
                camera=camera,
                passed=passed,
                data=data,
                duration_ms=(time.perf_counter() - t0) * 1000.0,
                config_hash=catalog.config_hash,
                request_id=request_id,
                peer=peer,
                image=image,
                error=error,
            )
        )

    def _capture_timeout(self, deadline_ms: float | None) -> float:
        if deadline_ms is None:
            return self.settings.capture_timeout_s
        return min(self.settings.capture_timeout_s, deadline_ms / 1000.0)

    async def run_capture(self, request: Capture) -> Frames:
        """CAPTURE: ``count`` distinct frames from a server camera."""
        with self.catalog.lease_newest() as lease:
            return await self._run_capture(request, lease.catalog)

    async def _run_capture(self, request: Capture, catalog: Catalog) -> Frames:
        rid = request.request_id
        camera = catalog.camera(request.camera, request_id=rid)
        if camera.source == "request":
            raise InvalidArgument(
                f"camera {camera.name!r} gets its images from the request: it cannot capture",
                request_id=rid,
            )
        if request.count > MAX_CAPTURE_FRAMES:
            raise InvalidArgument(
                f"count {request.count} is above the limit of {MAX_CAPTURE_FRAMES} frames",
                request_id=rid,
            )
        if request.depth and not camera.has_depth:
            raise InvalidArgument(f"camera {camera.name!r} has no depth", request_id=rid)
        encoding = None
        if request.encoding is not None:
            try:
                encoding = ImageEncoding(request.encoding)
            except ValueError:
                encoding = None
            if encoding not in (ImageEncoding.PNG, ImageEncoding.JPEG, None):
                encoding = None
            if encoding is None:
                raise InvalidArgument(
                    f"encoding {request.encoding!r}: CAPTURE takes 'png' or 'jpeg' "
                    "(or nothing, for raw frames)",
                    request_id=rid,
                )
        timeout_s = self._capture_timeout(request.deadline_ms)

        def work() -> tuple[list[ImagePayload], list[float]]:
            frames = _grab(camera, request.count, timeout_s, rid)
            payloads: list[ImagePayload] = []
            for frame in frames:
                payloads.append(payload_from_array(frame.color, encoding=encoding))
                if request.depth and frame.depth is not None:
                    payloads.append(payload_from_array(frame.depth, role=ImageRole.DEPTH))
            return payloads, [f.timestamp for f in frames]

        payloads, stamps = await self._in_pool(work, rid, request.deadline_ms, hold=catalog)
        intrinsics = None if camera.intrinsics is None else camera.intrinsics.to_dict()
        return Frames(rid, camera.name, tuple(payloads), tuple(stamps), intrinsics)

    def reload(self) -> Catalog:
        """Re-read the configuration through ``reloader`` and serve new requests with it.
        Raises whatever the reloader raises (the old catalog stays)."""
        if self.reloader is None:
            raise InvalidArgument("this server was started without a configuration file")
        catalog = self.reloader()
        self.replace_catalog(catalog)
        log.info("configuration reloaded (config hash %s)", catalog.config_hash)
        return catalog

    async def _in_pool(
        self,
        fn: Callable[[], _T],
        request_id: int,
        deadline_ms: float | None,
        *,
        hold: Catalog | None = None,
    ) -> _T:
        """Run ``fn`` in the pool. ``hold``: a catalog ``fn`` uses, leased until ``fn``
        returns, which may be after the request gave up (its deadline passed)."""
        if hold is not None:
            lease = hold.acquire()

            def leased() -> _T:
                with lease:
                    return fn()

            future = self._pool.try_submit(leased)
            if future is None:
                lease.release()
        else:
            future = self._pool.try_submit(fn)
        if future is None:
            raise Busy(
                f"all {self._pool.capacity} inspection slots are taken; try again",
                request_id=request_id,
            )
        if deadline_ms is None:
            return await future
        try:
            async with asyncio.timeout(deadline_ms / 1000.0):
                return await asyncio.shield(future)
        except TimeoutError:
            raise DeadlineExceeded(
                f"not done within the request's deadline of {deadline_ms:g} ms",
                request_id=request_id,
            ) from None


def _grab(camera: Camera, count: int, timeout_s: float, request_id: int) -> list[CameraFrame]:
    try:
        return camera.grab_many(count, timeout_s=timeout_s)
    except CellvisionError as exc:
        exc.request_id = request_id
        raise


@dataclass(frozen=True)
class ResultRecord:
    """What the server tells its result log about one answered inspection."""

    result: Result
    request: Inspect
    compute_ms: float


def _decode_input(
    images: tuple[ImagePayload, ...],
    request_id: int,
    uses_depth: bool,
    name: str,
    max_pixels: int,
) -> InspectionInput:
    colors = [p for p in images if p.role is ImageRole.COLOR]
    depths = [p for p in images if p.role is ImageRole.DEPTH]
    if len(colors) != 1:
        raise BadImage(
            f"inspection {name!r} takes exactly one colour image, the request has {len(colors)}",
            request_id=request_id,
        )
    if depths and not uses_depth:
        raise BadImage(
            f"inspection {name!r} takes no depth image, the request has {len(depths)}",
            request_id=request_id,
        )
    color = array_from_payload(colors[0], request_id=request_id, max_pixels=max_pixels)
    if color.dtype != "uint8":
        raise BadImage(
            f"the colour image must be 8-bit (gray8, bgr8, 8-bit PNG/JPEG), got {color.dtype}",
            request_id=request_id,
        )
    depth = []
    for index, payload in enumerate(depths):
        frame = array_from_payload(payload, request_id=request_id, max_pixels=max_pixels)
        if frame.dtype != "uint16" or frame.ndim != 2:
            raise BadImage(
                f"depth image {index} must be uint16 millimetres (depth16 or 16-bit PNG), "
                f"got {frame.dtype} with shape {frame.shape}",
                request_id=request_id,
            )
        if frame.shape != color.shape[:2]:
            raise BadImage(
                f"depth image {index} is {frame.shape[1]}x{frame.shape[0]}, the colour image "
                f"is {color.shape[1]}x{color.shape[0]}: they must be registered",
                request_id=request_id,
            )
        depth.append(frame)
    return InspectionInput(color, tuple(depth))


def _late_error(conn: Connection, exc: CellvisionError) -> bytes:
    """Bytes of an ERROR sent outside the normal flow (before HELLO, or after a fatal error)."""
    try:
        return conn.send(Error.from_exception(exc))
    except LocalProtocolError:
        return Error.from_exception(exc).to_frame(conn.wire_version).serialize()


class _ClientSession:
    """One accepted connection."""

    def __init__(
        self, server: VisionServer, reader: asyncio.StreamReader, writer: asyncio.StreamWriter
    ) -> None:
        self.server = server
        self.reader = reader
        self.writer = writer
        self.conn = Connection(
            Role.SERVER, limits=server.settings.limits(), versions=SUPPORTED_VERSIONS
        )
        self.finished = asyncio.Event()
        self._shutdown = asyncio.Event()
        self._tasks: set[asyncio.Task[None]] = set()
        peer = writer.get_extra_info("peername")
        self.peer = f"{peer[0]}:{peer[1]}" if isinstance(peer, tuple) else str(peer)

    def begin_shutdown(self) -> None:
        self._shutdown.set()

    async def run(self) -> None:
        try:
            async with asyncio.TaskGroup() as group:
                graceful = await self._read_loop(group)
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
            self.writer.close()
            with contextlib.suppress(Exception):
                await self.writer.wait_closed()
            self.finished.set()

    async def _read_loop(self, group: asyncio.TaskGroup) -> bool:
        """Read and dispatch until the peer closes (True) or broke the protocol (False)."""
        handshake_deadline = time.monotonic() + self.server.settings.handshake_timeout_s
        while True:
            # Backpressure: do not read more while the peer is not reading our answers.
            await self._drain()
            read = asyncio.ensure_future(self.reader.read(READ_CHUNK))
            stop = asyncio.ensure_future(self._shutdown.wait())
            timeout = None
            if self.conn.state in (State.HANDSHAKE, State.HELLO_RECEIVED):
                timeout = max(handshake_deadline - time.monotonic(), 0.0)
            done, _ = await asyncio.wait(
                {read, stop}, timeout=timeout, return_when=asyncio.FIRST_COMPLETED
            )
            if read not in done:
                read.cancel()
                with contextlib.suppress(asyncio.CancelledError, ConnectionError):
                    await read
                if stop not in done:  # no HELLO in time
                    stop.cancel()
                    limit = self.server.settings.handshake_timeout_s
                    log.info("%s: no HELLO within %g s; closing", self.peer, limit)
                    self._write(Close(reason=f"no HELLO within {limit:g} s"))
                    await self._drain()
                    return False
                await self._shutdown_session()
                return True
            stop.cancel()
            data = read.result()
            self.conn.receive_data(data)
            while True:
                try:
                    event = self.conn.next_event()
                except CellvisionError as exc:
                    log.info("%s: %s: %s", self.peer, exc.code.name, exc.message)
                    if exc.fatal:
                        self.writer.write(_late_error(self.conn, exc))
                        await self._drain()
                        return False
                    # Request id 0 (e.g. a request sent with id 0) gets a connection-level
                    # ERROR: SPEC §6.1 and §7 want an answer even then.
                    self._write(Error.from_exception(exc))
                    continue
                if event is NEED_DATA:
                    break
                if isinstance(event, ConnectionClosed):
                    return True
                assert isinstance(event, Message)
                if not self._dispatch(event, group):
                    return self.conn.state is not State.CLOSED

    def _dispatch(self, message: Message, group: asyncio.TaskGroup) -> bool:
        """Answer or start one request; False when the connection is to close."""
        if isinstance(message, Hello):
            return self._handshake(message)
        if isinstance(message, Ping):
            self._write(Pong(message.request_id, message.data))
            return True
        if isinstance(message, ListInspections):
            self._write(
                Inspections(message.request_id, self.server.catalog.inspection_descriptors())
            )
            return True
        if isinstance(message, Close):
            return False  # the TaskGroup finishes what is in flight, then CLOSE goes out
        if isinstance(message, Reload):
            task = group.create_task(self._reload(message))
            self._tasks.add(task)
            task.add_done_callback(self._tasks.discard)
            return True
        if isinstance(message, Inspect | Capture):
            if len(self.conn.pending) > self.server.settings.max_in_flight:
                self._write(
                    Error.from_exception(
                        Busy(
                            f"more than {self.server.settings.max_in_flight} requests in flight on "
                            "this connection",
                            request_id=message.request_id,
                        )
                    )
                )
                return True
            task = group.create_task(self._answer(message))
            self._tasks.add(task)
            task.add_done_callback(self._tasks.discard)
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
        expected = self.server.settings.auth_token
        if expected is not None:
            given = hello.auth_token or ""
            if not hmac.compare_digest(given.encode(), expected.encode()):
                self._write(
                    Error.from_exception(
                        NotAuthenticated(
                            "missing or wrong auth_token in HELLO", request_id=hello.request_id
                        )
                    )
                )
                return False
        settings = self.server.settings
        catalog = self.server.catalog
        self._write(
            Welcome(
                hello.request_id,
                version,
                settings.name,
                __version__,
                {
                    "max_frame_bytes": settings.max_frame_bytes,
                    "max_image_pixels": settings.max_image_pixels,
                    "max_in_flight": settings.max_in_flight,
                },
                catalog.inspection_descriptors(),
                catalog.camera_descriptors(),
            )
        )
        log.info("%s: handshake done (version %d.%d, client %r)", self.peer, *version, hello.client)
        return True

    async def _answer(self, request: Inspect | Capture) -> None:
        try:
            if isinstance(request, Inspect):
                response: Message = await self.server.run_inspection(request, peer=self.peer)
            else:
                response = await self.server.run_capture(request)
        except CellvisionError as exc:
            response = Error.from_exception(exc, request_id=request.request_id)
        except Exception as exc:  # a bug in an inspection must not take the server down
            log.exception("%s: request %d failed", self.peer, request.request_id)
            response = Error.from_exception(
                InternalError(f"{type(exc).__name__}: {exc}", request_id=request.request_id)
            )
        if request.request_id in self.conn.pending:
            try:
                self._write(response)
            except (TypeError, ValueError) as exc:
                # Data JSON cannot carry (numpy scalars, NaN): fail this request, not the
                # connection (the state machine is unchanged when serializing fails).
                log.error(
                    "%s: answer to request %d not sendable: %s", self.peer, request.request_id, exc
                )
                self._write(
                    Error.from_exception(
                        InternalError(
                            f"the server could not encode its answer: {exc}",
                            request_id=request.request_id,
                        )
                    )
                )
            await self._drain()

    async def _reload(self, request: Reload) -> None:
        rid = request.request_id
        response: Message
        if not self.server.settings.allow_reload or self.server.reloader is None:
            why = (
                "this server was started without a configuration file"
                if self.server.reloader is None
                else "reload is disabled (allow_reload: false)"
            )
            response = Error.from_exception(InvalidArgument(why, request_id=rid))
        else:
            try:
                catalog = await asyncio.to_thread(self.server.reload)
            except CellvisionError as exc:
                response = Error.from_exception(exc, request_id=rid)
            except ValueError as exc:  # ConfigError: the old configuration stays
                log.error("%s: reload refused, the old configuration stays: %s", self.peer, exc)
                response = Error.from_exception(ConfigInvalid(str(exc), request_id=rid))
            else:
                response = Reloaded(
                    rid,
                    catalog.config_hash,
                    catalog.inspection_descriptors(),
                    catalog.camera_descriptors(),
                )
        if rid in self.conn.pending:
            self._write(response)
            await self._drain()

    async def _shutdown_session(self) -> None:
        grace = self.server.settings.shutdown_grace_s
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
        try:
            data = self.conn.send(message)
        except LocalProtocolError:
            log.warning(
                "%s: dropped %s that the state machine refused", self.peer, message.TYPE.name
            )
            return
        if not self.writer.is_closing():
            self.writer.write(data)

    async def _drain(self) -> None:
        if not self.writer.is_closing():
            await self.writer.drain()
