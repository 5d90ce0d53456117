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
import time
from collections.abc import Callable, Coroutine
from dataclasses import dataclass, field, replace
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
from protocol.constants import HEADER_SIZE, SUPPORTED_VERSIONS, MessageType
from protocol.frames import Header, encode_metadata
from protocol.images import compressed_header

from .admission import Admission, ByteBudget, WorkPool
from .cameras import Camera, CameraFrame
from .catalog import Catalog, Image, InspectionInput, InspectionOutcome
from .results import ResultEntry, ResultLog

__version__ = "0.1.0"
log = logging.getLogger("vision_server")
_T = TypeVar("_T")

READ_CHUNK = 256 * 1024
DEFAULT_MAX_FRAME_BYTES = Limits().max_frame_bytes
"""What a client accepts when its HELLO does not say (SPEC §3.4 default)."""
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
    """How long a new connection may take to complete its TLS handshake (if any) and HELLO; then
    it is closed, so that silent connections cannot hold every one of the ``max_connections``
    slots."""
    idle_timeout_s: float = 60.0
    """How long an open connection may stay silent with nothing in flight before the server
    closes it (CLOSE). Announced in WELCOME; clients keep a connection alive with PING."""
    frame_timeout_s: float = 30.0
    """How long one frame may take to arrive, from its first byte to its last."""
    write_timeout_s: float = 30.0
    """How long the server waits for a client that does not read its answers before it drops
    the connection (a slow reader must not hold the server's memory)."""
    max_buffered_bytes: int = 256 * 1024 * 1024
    """Server-wide budget for request bodies and replies held in memory; a frame or a reply that
    does not fit is answered BUSY instead of being read or built."""

    def __post_init__(self) -> None:
        # "" would read as "a token is required" and let in every client that sends none.
        if self.auth_token is not None and not self.auth_token.strip():
            raise ValueError("auth_token is empty: give a token, or None for no authentication")

    def limits(self) -> Limits:
        return Limits(max_frame_bytes=self.max_frame_bytes, max_image_pixels=self.max_image_pixels)

    def welcome_limits(self) -> dict[str, int]:
        """The limits announced in WELCOME (SPEC §3.4, §5.2); durations in milliseconds."""
        limits = self.limits()
        return {
            "max_frame_bytes": self.max_frame_bytes,
            "max_metadata_bytes": limits.max_metadata_bytes,
            "max_blobs": limits.max_blobs,
            "max_image_pixels": self.max_image_pixels,
            # What a client can count on: on an idle server, this many pipelined requests
            # are all run (the pool's slots bound it too; others' requests share them).
            "max_in_flight": min(self.max_in_flight, self.workers + self.queue_depth),
            "max_connections": self.max_connections,
            "handshake_timeout_ms": round(self.handshake_timeout_s * 1000),
            "idle_timeout_ms": round(self.idle_timeout_s * 1000),
            "frame_timeout_ms": round(self.frame_timeout_s * 1000),
            # The default deadline of a server camera's frames (INSPECT without images, CAPTURE)
            # when the request sets none; work on a request's own images has no default.
            "capture_timeout_ms": round(self.capture_timeout_s * 1000),
        }

    def ssl_context(self) -> ssl.SSLContext | None:
        if not self.tls_cert:
            return None
        context = ssl.create_default_context(ssl.Purpose.CLIENT_AUTH)
        context.load_cert_chain(self.tls_cert, self.tls_key)
        return context


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
        self._budget = ByteBudget(self.settings.max_buffered_bytes)
        self._refusing = 0
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
        # TLS is started per connection in _accept, after the connection is counted, so that
        # connections still in the TLS handshake count towards max_connections and time out.
        self._ssl = self.settings.ssl_context()
        self._server = await asyncio.start_server(
            self._accept, self.settings.host, self.settings.port, limit=READ_CHUNK
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
            # Refusing politely costs a read (and a TLS handshake); never more of them at once
            # than connections: past that, a flood is just closed.
            if self._refusing >= self.settings.max_connections:
                writer.transport.abort()
                return
            self._refusing += 1
            try:
                if await self._start_tls(writer, REFUSE_HELLO_TIMEOUT_S):
                    await self._refuse(reader, writer, reason)
            finally:
                self._refusing -= 1
            return
        session = _ClientSession(self, reader, writer)
        self._connections.add(session)
        try:
            if await self._start_tls(writer, self.settings.handshake_timeout_s):
                await session.run()
        finally:
            self._connections.discard(session)
            session.admission_cleanup()

    async def _start_tls(self, writer: asyncio.StreamWriter, timeout_s: float) -> bool:
        """Wrap the connection in TLS when the server has TLS; False (and closed) on failure."""
        if self._ssl is None:
            return True
        try:
            await writer.start_tls(self._ssl, ssl_handshake_timeout=timeout_s)
        except Exception as exc:  # noqa: BLE001 - whatever the peer did, only it is dropped
            log.info("TLS handshake failed: %s", exc or type(exc).__name__)
            writer.transport.abort()
            return False
        return True

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

    async def run_inspection(
        self, request: Inspect, *, peer: str = "", admission: Admission | None = None
    ) -> Result:
        """Get the images (from the request or the camera), run the named inspection in the
        pool, record it in the result log, build the RESULT."""
        # The lease keeps the catalog's cameras open until this request is done with them.
        with self.catalog.lease_newest() as lease:
            return await self._run_inspection(request, lease.catalog, peer, admission)

    async def _run_inspection(
        self, request: Inspect, catalog: Catalog, peer: str, admission: Admission | None
    ) -> Result:
        started = time.perf_counter()
        rid = request.request_id
        inspection = catalog.inspection(request.inspection, request_id=rid)
        inspection = catalog.tuned(inspection, request.options, request_id=rid)
        camera = catalog.camera(inspection.camera, request_id=rid)
        acquire: Callable[[], InspectionInput]
        sources: list[str] = []  # the files a folder camera read: which images this is about
        if request.images:
            # Images in the request are inspected whatever the camera: a tool camera's, or a
            # stored image run through a fixed camera's inspection (SPEC §6.3).

            def acquire() -> InspectionInput:
                decoded = _decode_input(
                    request.images,
                    rid,
                    inspection.uses_depth,
                    inspection.name,
                    self.settings.max_image_pixels,
                )
                return InspectionInput(decoded.color, decoded.depth, camera.intrinsics)

        elif camera.source == "request":
            raise BadImage(
                f"inspection {inspection.name!r} uses camera {camera.name!r}, whose images "
                "arrive in the request, and the request has none",
                request_id=rid,
            )
        else:
            timeout_s = self._capture_timeout(request.deadline_ms)

            def acquire() -> InspectionInput:
                frames = _grab(camera, inspection.frames, timeout_s, rid)
                sources.extend(f.source for f in frames if f.source is not None)
                depth = tuple(f.depth for f in frames if f.depth is not None)
                return InspectionInput(
                    frames[0].color, depth if inspection.uses_depth else (), camera.intrinsics
                )

        def work() -> tuple[InspectionOutcome, float, tuple[ImagePayload, ...], bool | None]:
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
            if sources:
                outcome = replace(outcome, data={**outcome.data, "source_files": sources})
            stored = self._record(
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
            return outcome, compute_ms, images, stored

        outcome, compute_ms, images, stored = await self._in_pool(
            work, rid, request.deadline_ms, admission, hold=catalog
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
            stored,
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
    ) -> bool | None:
        """Log one run before its answer is sent; return whether the row was written (None
        without a result log). The log never raises: a full disk is counted and logged, the
        answer still goes out, with ``stored: false`` (SPEC §6.3), and :meth:`health` turns
        not ok. An error row that fails is counted the same way (its ERROR carries no flag)."""
        if self.results is None:
            return None
        row_id = self.results.record(
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
        return row_id is not None

    def health(self) -> dict[str, Any]:
        """The health report a PONG carries (SPEC §5.5): ``ok`` false once the result log lost
        a row since start (see :meth:`ResultLog.health`), and the log's counters."""
        report: dict[str, Any] = {"ok": True, "admission": self.admission_counters()}
        if self.results is not None:
            result_log = self.results.health()
            report["ok"] = bool(result_log["ok"])
            report["result_log"] = result_log
        return report

    def admission_counters(self) -> dict[str, Any]:
        """What bounds the server now: connections, worker slots, the byte budget."""
        return {
            "connections": len(self._connections),
            "max_connections": self.settings.max_connections,
            "pool_admitted": self._pool.admitted,
            "pool_capacity": self._pool.capacity,
            "buffered_bytes": self._budget.used,
            "buffered_bytes_peak": self._budget.peak,
            "max_buffered_bytes": self._budget.limit,
            "buffer_refusals": self._budget.refused,
        }

    def _capture_timeout(self, deadline_ms: float | None) -> float:
        if deadline_ms is None:
            return self.settings.capture_timeout_s
        return min(self.settings.capture_timeout_s, deadline_ms / 1000.0)

    async def run_capture(
        self,
        request: Capture,
        *,
        admission: Admission | None = None,
        max_reply_bytes: int = DEFAULT_MAX_FRAME_BYTES,
    ) -> Frames:
        """CAPTURE: ``count`` distinct frames from a server camera.

        The reply is bounded in bytes, not in frames: it must fit ``max_reply_bytes`` (what the
        client said it accepts, SPEC §5.1) and the server's byte budget, checked before the
        frames are taken (from the camera's declared size, or its first frame)."""
        with self.catalog.lease_newest() as lease:
            return await self._run_capture(request, lease.catalog, admission, max_reply_bytes)

    async def _run_capture(
        self,
        request: Capture,
        catalog: Catalog,
        admission: Admission | None,
        max_reply_bytes: int,
    ) -> Frames:
        rid = request.request_id
        camera = catalog.camera(request.camera, request_id=rid)
        if camera.source == "request":
            raise InvalidArgument(
                f"camera {camera.name!r} gets its images from the request: it cannot capture",
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
            frames = _capture_frames(
                camera,
                request.count,
                timeout_s,
                rid,
                lambda first: self._admit_reply(
                    request, first, encoding, admission, max_reply_bytes
                ),
            )
            payloads: list[ImagePayload] = []
            for frame in frames:
                payloads.append(payload_from_array(frame.color, encoding=encoding))
                if request.depth and frame.depth is not None:
                    payloads.append(payload_from_array(frame.depth, role=ImageRole.DEPTH))
            return payloads, [f.timestamp for f in frames]

        payloads, stamps = await self._in_pool(
            work, rid, request.deadline_ms, admission, hold=catalog
        )
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

    def _admit_reply(
        self,
        request: Capture,
        first: CameraFrame,
        encoding: ImageEncoding | None,
        admission: Admission | None,
        max_reply_bytes: int,
    ) -> None:
        """Refuse a CAPTURE whose reply could not be received or held, before grabbing the rest
        of its frames. Raw sizes bound the encoded ones (checked again when sent)."""
        rid = request.request_id
        per_frame = first.color.nbytes
        if encoding is not None:
            # Compressed frames of one scene have similar sizes; twice the first one's, at most
            # raw, bounds them (and the encoded reply is checked again before it is sent).
            encoded = len(payload_from_array(first.color, encoding=encoding).data)
            per_frame = min(per_frame, 2 * encoded)
        if request.depth and first.depth is not None:
            per_frame += first.depth.nbytes
        estimate = per_frame * request.count + _REPLY_OVERHEAD
        limit = min(max_reply_bytes, self.settings.max_buffered_bytes)
        if estimate > limit:
            who = (
                "the client accepts (HELLO max_frame_bytes)"
                if limit == max_reply_bytes
                else "the server may hold for replies (max_buffered_bytes)"
            )
            raise InvalidArgument(
                f"{request.count} frames of about {per_frame} bytes each make a reply of about "
                f"{estimate} bytes, more than the {limit} bytes {who}; ask for fewer frames "
                "or a compressed encoding",
                request_id=rid,
                details={"size": estimate, "max_size": limit},
            )
        if admission is not None and not admission.take_bytes(estimate):
            raise Busy(
                f"the server's memory for replies is taken ({self._budget.used} of "
                f"{self._budget.limit} bytes); try again",
                request_id=rid,
            )

    async def _in_pool(
        self,
        fn: Callable[[], _T],
        request_id: int,
        deadline_ms: float | None,
        admission: Admission | None = None,
        *,
        hold: Catalog | None = None,
    ) -> _T:
        """Run ``fn`` in the pool, on the slot ``admission`` reserved if it holds one.
        ``hold``: a catalog ``fn`` uses, leased until ``fn`` returns, which may be after the
        request gave up (its deadline passed)."""
        work = fn
        lease = None
        if hold is not None:
            lease = hold.acquire()

            def leased() -> _T:
                with lease:
                    return fn()

            work = leased
        future: asyncio.Future[_T] | None
        if admission is not None and admission.hand_slot_to_pool():
            future = self._pool.submit_reserved(work)
        else:
            future = self._pool.try_submit(work)
        if future is None and lease is not None:
            lease.release()
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


_REPLY_OVERHEAD = 64 * 1024
"""Bytes of a FRAMES reply besides the pixels (header, metadata, blob table), generously."""


def _capture_frames(
    camera: Camera,
    count: int,
    timeout_s: float,
    request_id: int,
    admit: Callable[[CameraFrame], None],
) -> list[CameraFrame]:
    """``count`` distinct successive frames; ``admit(first frame)`` may refuse the rest (a reply
    too large) before they are taken."""
    deadline = time.monotonic() + timeout_s
    first = _grab(camera, 1, timeout_s, request_id)[0]
    admit(first)
    frames = [first]
    try:
        while len(frames) < count:
            remaining = max(deadline - time.monotonic(), 0.0)
            frames.append(camera.grab(timeout_s=remaining, newer_than=frames[-1].index))
    except CellvisionError as exc:
        exc.request_id = request_id
        exc.message = f"got {len(frames)} of {count} frames within {timeout_s:.3g} s: {exc.message}"
        raise
    return frames


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
    # Every header is read before anything is decoded: a 16-bit colour PNG, or a colour depth
    # image, is refused without decompressing it (the decoded array is checked again below).
    for payload in (colors[0], *depths):
        if payload.encoding.is_raw:
            continue
        header = compressed_header(payload, request_id=request_id, max_pixels=max_pixels)
        if payload.role is ImageRole.COLOR and header.bits != 8:
            raise BadImage(
                f"the colour image is a {header.bits}-bit {payload.encoding}; it must be 8-bit",
                request_id=request_id,
            )
        if payload.role is ImageRole.DEPTH and (header.bits, header.channels) != (16, 1):
            raise BadImage(
                f"a depth image must be 16-bit gray (millimetres); this {payload.encoding} has "
                f"{header.channels} channel(s) of {header.bits} bits",
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
    """One accepted connection.

    Every frame is admitted when its header arrives (:meth:`_admit`): the state machine, the
    connection's in-flight limit, a pool slot for INSPECT/CAPTURE and the bytes of a large body
    from the server's budget; a refused frame is answered (BUSY …) and its body skipped unread.
    What a request holds is released once its answer has been handed to the socket and drained.
    """

    def __init__(
        self, server: VisionServer, reader: asyncio.StreamReader, writer: asyncio.StreamWriter
    ) -> None:
        self.server = server
        self.reader = reader
        self.writer = writer
        self.conn = Connection(
            Role.SERVER,
            limits=server.settings.limits(),
            versions=SUPPORTED_VERSIONS,
            admit=self._admit,
        )
        self.finished = asyncio.Event()
        self.handshake_deadline = time.monotonic() + server.settings.handshake_timeout_s
        """The TLS handshake and HELLO must be done by then (monotonic seconds)."""
        self.max_reply_bytes = DEFAULT_MAX_FRAME_BYTES
        """The largest frame the client accepts (its HELLO's max_frame_bytes)."""
        self._shutdown = asyncio.Event()
        self._tasks: set[asyncio.Task[None]] = set()
        self._tasks_done = asyncio.Event()
        """Set when the last request task of the connection has finished."""
        self._frame_admission: Admission | None = None
        self._held: set[Admission] = set()
        self._last_activity = time.monotonic()
        self._frame_started: float | None = None
        peer = writer.get_extra_info("peername")
        self.peer = f"{peer[0]}:{peer[1]}" if isinstance(peer, tuple) else str(peer)

    def begin_shutdown(self) -> None:
        self._shutdown.set()

    # ------------------------------------------------------------------ admission

    def _admit(self, header: Header) -> None:
        """Called by the connection with each header the state machine accepts, before the
        body is kept. Raises BUSY to refuse; the body is then skipped."""
        settings = self.server.settings
        admission = Admission(self.server._pool, self.server._budget)
        rid = header.request_id
        mtype = header.type
        if mtype in (MessageType.INSPECT, MessageType.CAPTURE):
            if len(self.conn.pending) >= settings.max_in_flight:
                raise Busy(
                    f"more than {settings.max_in_flight} requests in flight on this connection",
                    request_id=rid,
                )
            if not admission.take_slot():
                raise Busy(
                    f"all {self.server._pool.capacity} inspection slots are taken; try again",
                    request_id=rid,
                )
        # Small frames are bounded per connection (one frame at a time); a larger body is
        # only read when the server-wide budget can hold it.
        large = header.frame_length > self.conn.limits.max_handshake_frame_bytes
        if large and not admission.take_bytes(header.frame_length):
            admission.release()
            budget = self.server._budget
            raise Busy(
                f"the server's memory for request bodies is taken ({budget.used} of "
                f"{budget.limit} bytes); try again",
                request_id=rid,
                details={"size": header.frame_length},
            )
        self._frame_admission = admission
        self._held.add(admission)

    def _take_frame_admission(self) -> Admission | None:
        admission, self._frame_admission = self._frame_admission, None
        return admission

    def _release(self, admission: Admission | None) -> None:
        if admission is not None:
            admission.release()
            self._held.discard(admission)

    def admission_cleanup(self) -> None:
        """Give back everything this connection still holds (it is gone)."""
        for admission in list(self._held):
            self._release(admission)
        self._frame_admission = None

    # ------------------------------------------------------------------ the connection

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
            self.admission_cleanup()
            self.finished.set()

    def _read_timeout(self) -> tuple[float | None, str]:
        """Seconds until the connection has been silent too long, and what it then says."""
        settings = self.server.settings
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

    async def _read_loop(self, group: asyncio.TaskGroup) -> bool:
        """Read and dispatch until the peer closes (True) or broke the protocol (False)."""
        while True:
            # Backpressure: do not read more while the peer is not reading our answers.
            await self._drain()
            read = asyncio.ensure_future(self.reader.read(READ_CHUNK))
            stop = asyncio.ensure_future(self._shutdown.wait())
            timeout, why = self._read_timeout()
            waiters = {read, stop}
            # With requests in flight there is no idle timeout; wake up when the last one is
            # answered, so that a client that then goes silent is closed after idle_timeout_s.
            woken: asyncio.Future[Any] | None = None
            if timeout is None and self._tasks:
                self._tasks_done.clear()
                woken = asyncio.ensure_future(self._tasks_done.wait())
                waiters.add(woken)
            try:
                done, _ = await asyncio.wait(
                    waiters, timeout=timeout, return_when=asyncio.FIRST_COMPLETED
                )
            except asyncio.CancelledError:  # a request task failed: leave nothing pending
                read.cancel()
                stop.cancel()
                if woken is not None:
                    woken.cancel()
                raise
            if woken is not None:
                woken.cancel()
                if woken in done and read not in done and stop not in done:
                    read.cancel()
                    stop.cancel()
                    with contextlib.suppress(asyncio.CancelledError, ConnectionError):
                        await read
                    continue
            if read not in done:
                read.cancel()
                with contextlib.suppress(asyncio.CancelledError, ConnectionError):
                    await read
                if stop not in done:  # silent for too long
                    stop.cancel()
                    log.info("%s: %s; closing", self.peer, why)
                    self._write(Close(reason=why))
                    await self._drain()
                    return False
                await self._shutdown_session()
                return True
            stop.cancel()
            data = read.result()
            if data and self._frame_started is None:
                self._frame_started = time.monotonic()
            self.conn.receive_data(data)
            frame_ended = False
            while True:
                try:
                    event = self.conn.next_event()
                except CellvisionError as exc:
                    frame_ended = True
                    self._release(self._take_frame_admission())
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
                frame_ended = True
                if isinstance(event, ConnectionClosed):
                    return True
                assert isinstance(event, Message)
                self._last_activity = time.monotonic()
                admission = self._take_frame_admission()
                try:
                    keep_going = self._dispatch(event, group, admission)
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
        self, message: Message, group: asyncio.TaskGroup, admission: Admission | None
    ) -> bool:
        """Answer or start one request; False when the connection is to close. A request task
        takes over ``admission``; for everything else it is released here."""
        if isinstance(message, Inspect | Capture):
            self._start(group, self._answer(message, admission))
            return True
        self._release(admission)
        if isinstance(message, Hello):
            return self._handshake(message)
        if isinstance(message, Ping):
            self._write(Pong(message.request_id, message.data, self.server.health()))
            return True
        if isinstance(message, ListInspections):
            self._write(
                Inspections(message.request_id, self.server.catalog.inspection_descriptors())
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
            self._tasks_done.set()

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
        if hello.max_frame_bytes is not None:
            self.max_reply_bytes = hello.max_frame_bytes
        settings = self.server.settings
        catalog = self.server.catalog
        self._write(
            Welcome(
                hello.request_id,
                version,
                settings.name,
                __version__,
                settings.welcome_limits(),
                catalog.inspection_descriptors(),
                catalog.camera_descriptors(),
            )
        )
        log.info("%s: handshake done (version %d.%d, client %r)", self.peer, *version, hello.client)
        return True

    async def _answer(self, request: Inspect | Capture, admission: Admission | None) -> None:
        try:
            try:
                if isinstance(request, Inspect):
                    response: Message = await self.server.run_inspection(
                        request, peer=self.peer, admission=admission
                    )
                else:
                    response = await self.server.run_capture(
                        request, admission=admission, max_reply_bytes=self.max_reply_bytes
                    )
            except CellvisionError as exc:
                response = Error.from_exception(exc, request_id=request.request_id)
            except Exception as exc:  # a bug in an inspection must not take the server down
                log.exception("%s: request %d failed", self.peer, request.request_id)
                response = Error.from_exception(
                    InternalError(f"{type(exc).__name__}: {exc}", request_id=request.request_id)
                )
            if request.request_id in self.conn.pending:
                self._write(response)
                await self._drain()
        finally:
            # The reply is in the socket (or the connection is gone): its memory is free.
            self._release(admission)

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
                    catalog.notes,
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
        """Send ``message``. An answer the client could not receive (larger than its HELLO's
        max_frame_bytes) or cannot be encoded is replaced by an ERROR for its request."""
        try:
            data = self._encode(message)
        except LocalProtocolError:
            log.warning(
                "%s: dropped %s that the state machine refused", self.peer, message.TYPE.name
            )
            return
        if not self.writer.is_closing():
            self.writer.write(data)
            self._last_activity = time.monotonic()

    def _encode(self, message: Message) -> bytes:
        rid = message.request_id
        try:
            frame = message.to_frame(self.conn.wire_version)
            size = HEADER_SIZE + len(encode_metadata(frame.metadata))
            size += sum(4 + len(blob) for blob in frame.blobs)
        except (TypeError, ValueError) as exc:
            # Data JSON cannot carry (numpy scalars, NaN): fail this request, not the
            # connection (the state machine is unchanged when serializing fails).
            log.error("%s: answer to request %d not sendable: %s", self.peer, rid, exc)
            return self.conn.send(
                Error.from_exception(
                    InternalError(f"the server could not encode its answer: {exc}", request_id=rid)
                )
            )
        if size > self.max_reply_bytes and not isinstance(message, Error):
            log.warning(
                "%s: %s of %d bytes exceeds the client's limit", self.peer, message.TYPE.name, size
            )
            return self.conn.send(
                Error.from_exception(
                    InvalidArgument(
                        f"the answer ({message.TYPE.name}) is {size} bytes, more than the "
                        f"{self.max_reply_bytes} bytes the client accepts (HELLO "
                        "max_frame_bytes); ask for less (fewer frames, a compressed encoding, "
                        "no overlay)",
                        request_id=rid,
                        details={"size": size, "max_size": self.max_reply_bytes},
                    )
                )
            )
        return self.conn.send(message)

    async def _drain(self) -> None:
        """Wait until the client has taken our answers; drop a client that does not read."""
        if self.writer.is_closing():
            return
        try:
            async with asyncio.timeout(self.server.settings.write_timeout_s):
                await self.writer.drain()
        except TimeoutError:
            log.warning(
                "%s: the client has not read its answers for %g s; dropping it",
                self.peer,
                self.server.settings.write_timeout_s,
            )
            self.writer.transport.abort()
            raise ConnectionAbortedError("slow reader dropped") from None
