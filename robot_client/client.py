"""The asyncio client of a cellvision server, and a small synchronous facade.

Requests are matched to responses by id, so many may be in flight at once (pipelining) and
answers may come back in any order. A lost connection fails the requests in flight with
:class:`ConnectionLost`; the next request reconnects (with exponential backoff) when
``reconnect`` is on. A request whose fate is unknown is never re-sent automatically; one the
server refused with a non-fatal BUSY (not started) is, when ``busy_timeout_s`` is set.

Images travel without copies on this side: a numpy image is sent from the caller's array (a
view handed to the socket, no ``tobytes()``, no join), and answers are received straight into
their frame body (:mod:`wireio`), where an overlay's bytes stay.
"""

from __future__ import annotations

import asyncio
import contextlib
import itertools
import logging
import random
import ssl as ssl_module
import threading
import time
from collections.abc import Callable, Coroutine, Iterable, Sequence
from concurrent.futures import Future as ConcurrentFuture
from dataclasses import dataclass
from typing import Any, TypeVar

import numpy as np
import numpy.typing as npt

from protocol import (
    NEED_DATA,
    OPERATOR_CHOICES,
    SUPPORTED_VERSIONS,
    Busy,
    Capture,
    CellvisionError,
    Close,
    Connection,
    ConnectionClosed,
    Error,
    Frames,
    Hello,
    ImageEncoding,
    ImagePayload,
    ImageRole,
    Inspect,
    Inspections,
    Limits,
    ListInspections,
    Message,
    OperatorAnswer,
    OperatorCall,
    Ping,
    Pong,
    Result,
    Role,
    ShuttingDown,
    State,
    UnsupportedVersion,
    Welcome,
    array_from_payload,
    payload_from_array,
)
from wireio import WireStream, open_connection

from .errors import ClientClosed, ConnectionLost, NotCellvision, RequestTimeout

log = logging.getLogger("robot_client")
_T = TypeVar("_T")
_M = TypeVar("_M", bound=Message)

DEFAULT_MAX_FRAME_BYTES = 256 * 1024 * 1024
"""The largest answer the client accepts by default: room for a CAPTURE of 30 1024x768 colour
frames (70.8 MB), more than the protocol's 64 MiB default."""
ImageLike = npt.NDArray[Any] | ImagePayload
BUSY_BACKOFF_INITIAL_S = 0.005
BUSY_BACKOFF_MAX_S = 0.2
"""Without a retry-after hint, BUSY is retried after 5 ms, doubling up to 200 ms (jittered)."""
BUSY_JITTER = (0.8, 1.2)
"""Each wait after BUSY is scaled by a random factor in this range, so that clients refused
together do not come back together."""
_JITTER_RNG = random.Random()


@dataclass(frozen=True)
class ReconnectPolicy:
    """Reconnect with exponential backoff: ``initial_s``, doubling up to ``max_s``; give up
    after ``attempts`` tries (0: never reconnect)."""

    attempts: int = 5
    initial_s: float = 0.1
    max_s: float = 2.0

    def delays(self) -> Iterable[float]:
        delay = self.initial_s
        for _ in range(self.attempts):
            yield delay
            delay = min(delay * 2.0, self.max_s)


class VisionClient:
    """An asyncio client. Use ``async with VisionClient(host, port) as client``."""

    def __init__(
        self,
        host: str = "127.0.0.1",
        port: int = 7878,
        *,
        auth_token: str | None = None,
        client_name: str = "robot_client/0.1.0",
        connect_timeout_s: float = 5.0,
        request_timeout_s: float = 30.0,
        reconnect: ReconnectPolicy | None = None,
        ssl: ssl_module.SSLContext | None = None,
        max_frame_bytes: int = DEFAULT_MAX_FRAME_BYTES,
        keepalive: bool = True,
        busy_timeout_s: float | None = None,
    ) -> None:
        """``max_frame_bytes`` is the largest answer this client accepts; it is announced in
        HELLO, and the server answers a request whose reply would be larger with an ERROR.
        With ``keepalive``, an idle connection sends PING before the server's announced idle
        timeout closes it.

        ``busy_timeout_s``: an INSPECT or CAPTURE refused with a non-fatal BUSY is sent again
        after the server's ``retry_after_ms`` hint (or an exponential back-off, 5 ms doubling
        to 200 ms), jittered by 0.8-1.2x, until this many seconds have passed since the first
        send; then the last BUSY is raised. None (the default) raises BUSY at once. Retries are
        counted in ``busy_retries``."""
        self.host = host
        self.port = port
        self.auth_token = auth_token
        self.client_name = client_name
        self.connect_timeout_s = connect_timeout_s
        self.request_timeout_s = request_timeout_s
        self.reconnect = reconnect if reconnect is not None else ReconnectPolicy()
        self.ssl = ssl
        self.max_frame_bytes = max_frame_bytes
        self.keepalive = keepalive
        self.busy_timeout_s = busy_timeout_s
        self.busy_retries = 0
        """Requests sent again after a BUSY (see ``busy_timeout_s``)."""
        self._keepalive_task: asyncio.Task[None] | None = None
        self.welcome: Welcome | None = None
        self._conn: Connection | None = None
        self._stream: WireStream | None = None
        self._reader_task: asyncio.Task[None] | None = None
        self._pending: dict[int, asyncio.Future[Message]] = {}
        self._ids = itertools.count(1)
        self._connect_lock = asyncio.Lock()
        # Set whenever a request stops being in flight: wakes requests waiting for room.
        self._room = asyncio.Event()
        self._closed = False
        self.reconnects = 0

    # ------------------------------------------------------------------ connection

    @property
    def connected(self) -> bool:
        return self._conn is not None and self._conn.state is State.OPEN

    @property
    def stream(self) -> WireStream | None:
        """The stream of the current connection (None when not connected): its address
        (``get_extra_info``) and byte counters, for tools and tests."""
        return self._stream

    async def connect(self) -> Welcome:
        """Open the connection and do the handshake; returns the server's WELCOME."""
        async with self._connect_lock:
            if self.connected:
                assert self.welcome is not None
                return self.welcome
            return await self._open()

    async def _open(self) -> Welcome:
        conn = Connection(
            Role.CLIENT,
            limits=Limits(max_frame_bytes=self.max_frame_bytes),
            versions=SUPPORTED_VERSIONS,
        )
        try:
            async with asyncio.timeout(self.connect_timeout_s):
                stream = await open_connection(self.host, self.port, conn, ssl=self.ssl)
        except (OSError, TimeoutError) as exc:
            raise ConnectionLost(
                f"cannot connect to {self.host}:{self.port}: {exc or type(exc).__name__}"
            ) from exc
        self._conn, self._stream = conn, stream
        hello_id = self._new_id()
        future: asyncio.Future[Message] = asyncio.get_running_loop().create_future()
        self._pending[hello_id] = future
        self._reader_task = asyncio.create_task(self._read_loop(conn, stream))
        stream.writelines(
            conn.send_parts(
                Hello(
                    hello_id,
                    SUPPORTED_VERSIONS,
                    self.client_name,
                    self.auth_token,
                    self.max_frame_bytes,
                )
            )
        )
        try:
            async with asyncio.timeout(self.connect_timeout_s):
                await stream.drain()
                answer = await future
        except TimeoutError:
            await self._drop_connection(ConnectionLost("no WELCOME within the connect timeout"))
            raise ConnectionLost(
                f"{self.host}:{self.port} did not answer HELLO within {self.connect_timeout_s} s"
            ) from None
        except NotCellvision:
            await self._drop_connection(ConnectionLost("handshake failed"))
            raise
        except ConnectionLost as exc:
            await self._drop_connection(ConnectionLost("handshake failed"))
            if self.ssl is None:
                # A TLS server drops a plain-TCP HELLO without a word: say what it may mean.
                raise ConnectionLost(
                    f"{exc} before answering HELLO (if {self.host}:{self.port} requires TLS, "
                    "connect with TLS: --tls)"
                ) from exc
            raise
        except BaseException:
            await self._drop_connection(ConnectionLost("handshake failed"))
            raise
        assert isinstance(answer, Welcome)
        self.welcome = answer
        idle_ms = answer.limits.get("idle_timeout_ms", 0)
        if self.keepalive and isinstance(idle_ms, int) and idle_ms > 0:
            self._keepalive_task = asyncio.create_task(self._keep_alive(conn, idle_ms / 1000.0))
        return answer

    async def _keep_alive(self, conn: Connection, idle_timeout_s: float) -> None:
        """PING when nothing else has been sent for a third of the server's idle timeout, so
        that the server does not close a connection a robot holds between tasks (SPEC §5.5)."""
        interval = idle_timeout_s / 3.0
        while self._conn is conn and conn.state is State.OPEN:
            await asyncio.sleep(interval)
            if self._conn is conn and conn.state is State.OPEN and not conn.pending:
                with contextlib.suppress(CellvisionError, ConnectionLost, RequestTimeout):
                    await self.request(lambda rid: Ping(rid, "keepalive"), timeout_s=interval)

    async def close(self) -> None:
        """Graceful close: CLOSE, wait for the answers in flight and the server's CLOSE."""
        self._closed = True
        conn, stream, task = self._conn, self._stream, self._reader_task
        if conn is not None and stream is not None and conn.state is State.OPEN:
            with contextlib.suppress(Exception):
                stream.writelines(conn.send_parts(Close(reason="client done")))
                await stream.drain()
            if task is not None:
                with contextlib.suppress(Exception):
                    async with asyncio.timeout(self.connect_timeout_s):
                        await asyncio.shield(task)
        await self._drop_connection(ClientClosed("the client was closed"))

    async def __aenter__(self) -> VisionClient:
        await self.connect()
        return self

    async def __aexit__(self, *exc: object) -> None:
        await self.close()

    async def _drop_connection(self, reason: Exception) -> None:
        keepalive, self._keepalive_task = self._keepalive_task, None
        if keepalive is not None and keepalive is not asyncio.current_task():
            keepalive.cancel()
        task, stream = self._reader_task, self._stream
        self._reader_task = None
        self._stream = None
        self._conn = None
        if task is not None and task is not asyncio.current_task():
            task.cancel()
            with contextlib.suppress(BaseException):
                await task
        if stream is not None:
            stream.close()
            with contextlib.suppress(Exception):
                await stream.wait_closed()
        self._fail_all(reason)

    def _fail_all(self, reason: Exception) -> None:
        self._room.set()
        pending, self._pending = self._pending, {}
        for future in pending.values():
            if not future.done():
                future.set_exception(reason)

    async def _read_loop(self, conn: Connection, stream: WireStream) -> None:
        reason: Exception = ConnectionLost("the server closed the connection")
        try:
            while True:
                # The bytes go straight into the connection (an answer's body, no copy).
                await stream.receive()
                while True:
                    try:
                        event = conn.next_event()
                    except CellvisionError as exc:
                        if exc.fatal:
                            # Reported once, by the request or connect() it ends (a warning
                            # here printed it twice in the command-line tools).
                            log.debug("bad data from the server: %s", exc)
                            if isinstance(exc, UnsupportedVersion):
                                # E.g. a WELCOME of a version we do not speak: connect() must
                                # say so, not report a mere lost connection.
                                reason = exc
                            elif exc.details.get("text"):
                                reason = NotCellvision(
                                    f"{self.host}:{self.port} is not a cellvision server: it "
                                    f"answered in text ({exc.message}){_text_peer_hint(exc)}"
                                )
                            else:
                                reason = ConnectionLost(f"protocol error from the server: {exc}")
                            return
                        # An answer that could not be decoded fails its request now.
                        future = self._pending.pop(exc.request_id, None)
                        if future is not None and not future.done():
                            future.set_exception(exc)
                        else:  # no request to report it: the log is its only trace
                            log.warning("bad data from the server: %s", exc)
                        continue
                    if event is NEED_DATA:
                        break
                    if isinstance(event, ConnectionClosed):
                        return
                    assert isinstance(event, Message)
                    if isinstance(event, Close):
                        # SPEC §5.6: requests still in flight crossed the server's CLOSE and
                        # were not read, so they fail as SHUTTING_DOWN (not done, safe to retry).
                        reason = ShuttingDown(
                            f"the server closed the connection ({event.reason or 'no reason'}) "
                            "before reading this request"
                        )
                        return
                    self._deliver(event)
                    if isinstance(event, Error) and event.fatal:
                        reason = ConnectionLost(f"the server ended the connection: {event.message}")
                        return
        except (OSError, ConnectionError) as exc:
            reason = ConnectionLost(f"connection to {self.host}:{self.port} lost: {exc}")
        finally:
            if self._conn is conn:
                self._conn = None
                self._stream = None
                self._reader_task = None
                stream.close()
            self._fail_all(reason)

    def _deliver(self, message: Message) -> None:
        self._room.set()
        if isinstance(message, Error) and message.request_id == 0:
            log.warning("server error: %s %s", message.name, message.message)
            if message.fatal:
                self._fail_all(message.to_exception())
            return
        future = self._pending.pop(message.request_id, None)
        if future is None or future.done():
            return  # the request timed out on our side; its late answer is dropped
        if isinstance(message, Error):
            future.set_exception(message.to_exception())
        else:
            future.set_result(message)

    def _new_id(self) -> int:
        while True:
            rid = next(self._ids) & 0xFFFFFFFF
            if rid and rid not in self._pending:
                return rid

    async def _ensure_connected(self) -> tuple[Connection, WireStream]:
        if self._closed:
            raise ClientClosed("the client was closed")
        if self.connected and self._conn is not None and self._stream is not None:
            return self._conn, self._stream
        async with self._connect_lock:
            if not self.connected:
                if self.welcome is None:
                    await self._open()
                else:
                    await self._reconnect()
        if self._conn is None or self._stream is None:
            raise ConnectionLost(f"the connection to {self.host}:{self.port} dropped at once")
        return self._conn, self._stream

    async def _reconnect(self) -> None:
        last: Exception = ConnectionLost("reconnect is off")
        for delay in self.reconnect.delays():
            await asyncio.sleep(delay)
            try:
                await self._open()
                self.reconnects += 1
                log.info("reconnected to %s:%d", self.host, self.port)
                return
            except ConnectionLost as exc:
                last = exc
        raise ConnectionLost(
            f"could not reconnect to {self.host}:{self.port} after "
            f"{self.reconnect.attempts} attempts: {last}"
        )

    async def _wait_for_room(self, timeout_s: float) -> tuple[Connection, WireStream]:
        """The connection, once it has fewer requests in flight than the server's
        ``max_in_flight`` (SPEC §3.4: a client MUST NOT exceed it). Requests that timed out
        on our side still count until their late answer comes: the server is still on them.
        Raises RequestTimeout when no room is made within ``timeout_s``."""
        deadline = asyncio.get_running_loop().time() + timeout_s
        while True:
            conn, stream = await self._ensure_connected()
            welcome = self.welcome
            room = welcome.limits.get("max_in_flight", 0) if welcome is not None else 0
            if room <= 0 or len(conn.pending) < room:
                return conn, stream
            self._room.clear()
            try:
                async with asyncio.timeout_at(deadline):
                    await self._room.wait()
            except TimeoutError:
                raise RequestTimeout(
                    f"no room to send a request within {timeout_s:g} s: the server's "
                    f"max_in_flight ({room}) requests stay unanswered"
                ) from None

    async def request(
        self, build: Callable[[int], _M], *, timeout_s: float | None = None
    ) -> Message:
        """Send the request ``build(request_id)`` and wait for its answer.

        Raises the server's error as its :class:`protocol.CellvisionError` subclass,
        :class:`RequestTimeout` after ``timeout_s`` (default ``request_timeout_s``), or
        :class:`ConnectionLost`.
        """
        limit = self.request_timeout_s if timeout_s is None else timeout_s
        conn, stream = await self._wait_for_room(limit)
        rid = self._new_id()
        message = build(rid)
        future: asyncio.Future[Message] = asyncio.get_running_loop().create_future()
        self._pending[rid] = future
        try:
            # The frame's parts as they are: an image blob is a view of the caller's array.
            stream.writelines(conn.send_parts(message))
            await stream.drain()
        except (OSError, ConnectionError) as exc:
            self._pending.pop(rid, None)
            raise ConnectionLost(f"connection lost while sending: {exc}") from exc
        except BaseException:
            self._pending.pop(rid, None)
            raise
        try:
            async with asyncio.timeout(limit):
                return await future
        except TimeoutError:
            raise RequestTimeout(
                f"no answer to {message.TYPE.name} (id {rid}) within {limit:g} s"
            ) from None
        finally:
            self._pending.pop(rid, None)

    async def _request_work(
        self, build: Callable[[int], _M], *, timeout_s: float | None = None
    ) -> Message:
        """:meth:`request` for INSPECT and CAPTURE: a non-fatal BUSY is retried for up to
        ``busy_timeout_s`` (see the constructor), each time with a new request id."""
        if self.busy_timeout_s is None:
            return await self.request(build, timeout_s=timeout_s)
        loop = asyncio.get_running_loop()
        give_up = loop.time() + self.busy_timeout_s
        backoff_s = BUSY_BACKOFF_INITIAL_S
        while True:
            try:
                return await self.request(build, timeout_s=timeout_s)
            except Busy as exc:
                if exc.fatal:
                    raise
                wait_s = busy_wait_s(exc, backoff_s)
                if loop.time() + wait_s > give_up:
                    raise  # the next try would come after busy_timeout_s
                backoff_s = min(backoff_s * 2.0, BUSY_BACKOFF_MAX_S)
                log.debug("BUSY (%s); sending again in %.3f s", exc.message, wait_s)
                await asyncio.sleep(wait_s)
                self.busy_retries += 1

    # ------------------------------------------------------------------ requests

    async def ping(self, data: str = "") -> float:
        """Round-trip time of a PING, in seconds."""
        t0 = time.perf_counter()
        answer = await self.request(lambda rid: Ping(rid, data))
        assert isinstance(answer, Pong)
        return time.perf_counter() - t0

    async def list_inspections(self) -> tuple[dict[str, Any], ...]:
        answer = await self.request(ListInspections)
        assert isinstance(answer, Inspections)
        return answer.inspections

    async def inspect(
        self,
        inspection: str,
        image: ImageLike | None = None,
        *,
        depth: Sequence[ImageLike] = (),
        deadline_s: float | None = None,
        overlay: bool = False,
        options: dict[str, Any] | None = None,
        encoding: ImageEncoding | None = None,
        timeout_s: float | None = None,
    ) -> Result:
        """Run a named inspection, on ``image`` (and ``depth`` frames) if given, else on the
        server's camera. numpy images are sent raw unless ``encoding`` asks for PNG/JPEG.

        The verdict stands whatever ``result.stored`` says; ``stored`` is False when the server
        could not write the result to its log (SPEC §6.3), None when it keeps none. A program
        that must not go on without traceability checks it: no exception is raised for it."""
        images: list[ImagePayload] = []
        if image is not None:
            images.append(_payload(image, ImageRole.COLOR, encoding))
        images.extend(_payload(d, ImageRole.DEPTH, None) for d in depth)
        deadline_ms = None if deadline_s is None else deadline_s * 1000.0
        answer = await self._request_work(
            lambda rid: Inspect(
                rid, inspection, tuple(images), deadline_ms, overlay, dict(options or {})
            ),
            timeout_s=timeout_s,
        )
        assert isinstance(answer, Result)
        return answer

    async def capture(
        self,
        camera: str,
        *,
        count: int = 1,
        depth: bool = False,
        encoding: ImageEncoding | None = None,
        timeout_s: float | None = None,
    ) -> Frames:
        """``count`` distinct frames from a server camera (colour, plus depth when asked);
        colour raw, or PNG/JPEG with ``encoding``."""
        wire = None if encoding is None else ImageEncoding(encoding).value
        answer = await self._request_work(
            lambda rid: Capture(rid, camera, count, depth, wire), timeout_s=timeout_s
        )
        assert isinstance(answer, Frames)
        return answer

    async def operator_call(
        self,
        message: str,
        *,
        choices: Sequence[str] = OPERATOR_CHOICES,
        inspection: str = "",
        skill: str = "",
        images: Sequence[ImageLike] = (),
        deadline_s: float | None = None,
        result_id: int | None = None,
    ) -> OperatorAnswer:
        """Ask the person at the server's console (SPEC §6.6, protocol 1.1) and wait for the
        answer: ``retry``, ``continue`` or ``abort``, one of ``choices``, with who answered
        (``operator``, ``by``) and why (``reason``). ``images`` (arrays go as PNG; a RESULT's
        overlay payload as it came) show what failed; ``result_id`` (the failed RESULT's) has
        the server write the answer onto that result in its result log. The server answers
        DEADLINE_EXCEEDED after ``deadline_s``; this side waits a ``request_timeout_s`` longer
        (without a deadline: for days). A server without operator calls raises
        UnexpectedMessage or UnknownMessageType; a 1.0 server LocalProtocolError (not sent)."""
        payloads = tuple(_payload(i, ImageRole.COLOR, ImageEncoding.PNG) for i in images)
        deadline_ms = None if deadline_s is None else deadline_s * 1000.0
        wait_s = (deadline_s if deadline_s is not None else 7 * 86400.0) + self.request_timeout_s
        answer = await self.request(
            lambda rid: OperatorCall(
                rid, message, tuple(choices), inspection, skill, payloads, deadline_ms, result_id
            ),
            timeout_s=wait_s,
        )
        assert isinstance(answer, OperatorAnswer)
        return answer


def _text_peer_hint(exc: CellvisionError) -> str:
    """What a text answer to HELLO suggests: the port of another front-end."""
    if "HTTP" in exc.message:
        return (
            ": an HTTP server, e.g. the web console (default port 7880); the binary protocol's "
            "port is the one `vision-server serve` prints as 'listening on' (default 7878)"
        )
    return ": another text protocol (the line protocol's port, default 7879?)"


def retry_after_s(busy: Busy) -> float | None:
    """The server's hint in a BUSY (``details.retry_after_ms``: when a slot is expected to
    free), in seconds; None when it gives none (or nothing usable)."""
    hint = busy.details.get("retry_after_ms")
    if isinstance(hint, bool) or not isinstance(hint, int | float) or not hint >= 0:
        return None
    return float(hint) / 1000.0


def busy_wait_s(busy: Busy, backoff_s: float, rng: random.Random | None = None) -> float:
    """Seconds to wait before sending a request refused with ``busy`` again: the server's
    hint, else ``backoff_s``, scaled by a random factor in :data:`BUSY_JITTER`."""
    hinted_s = retry_after_s(busy)
    base_s = hinted_s if hinted_s is not None else backoff_s
    return base_s * (rng or _JITTER_RNG).uniform(*BUSY_JITTER)


def _payload(image: ImageLike, role: ImageRole, encoding: ImageEncoding | None) -> ImagePayload:
    if isinstance(image, ImagePayload):
        return image
    # Raw encodings view the array (a copy only when it is not C-contiguous little-endian).
    return payload_from_array(np.asarray(image), role=role, encoding=encoding)


def overlay_image(result: Result) -> npt.NDArray[Any] | None:
    """The overlay image of a RESULT (BGR uint8), if the server sent one."""
    for payload in result.images:
        if payload.role is ImageRole.OVERLAY:
            return array_from_payload(payload)
    return None


class SyncVisionClient:
    """A blocking facade over :class:`VisionClient` for scripts and robot programs that are
    not asyncio: it runs a private event loop in a background thread. Keyword arguments are
    VisionClient's (``request_timeout_s``, ``busy_timeout_s`` ...)."""

    def __init__(self, host: str = "127.0.0.1", port: int = 7878, **kwargs: Any) -> None:
        self._loop = asyncio.new_event_loop()
        self._thread = threading.Thread(
            target=self._loop.run_forever, name="vision-client", daemon=True
        )
        self._thread.start()
        self._client: VisionClient = self._call(_make_client(host, port, kwargs))
        try:
            self.welcome: Welcome = self._call(self._client.connect())
        except BaseException:
            self._stop_loop()
            raise

    def _call(self, coro: Coroutine[Any, Any, _T]) -> _T:
        future: ConcurrentFuture[_T] = asyncio.run_coroutine_threadsafe(coro, self._loop)
        return future.result()

    def ping(self, data: str = "") -> float:
        return self._call(self._client.ping(data))

    def list_inspections(self) -> tuple[dict[str, Any], ...]:
        return self._call(self._client.list_inspections())

    def inspect(self, inspection: str, image: ImageLike | None = None, **kwargs: Any) -> Result:
        return self._call(self._client.inspect(inspection, image, **kwargs))

    def capture(self, camera: str, **kwargs: Any) -> Frames:
        return self._call(self._client.capture(camera, **kwargs))

    def operator_call(self, message: str, **kwargs: Any) -> OperatorAnswer:
        """See :meth:`VisionClient.operator_call` (blocks until the person answers)."""
        return self._call(self._client.operator_call(message, **kwargs))

    @property
    def busy_retries(self) -> int:
        """Requests sent again after a BUSY (see VisionClient's ``busy_timeout_s``)."""
        return self._client.busy_retries

    def close(self) -> None:
        if self._loop.is_running():
            with contextlib.suppress(Exception):
                self._call(self._client.close())
            self._stop_loop()

    def _stop_loop(self) -> None:
        self._loop.call_soon_threadsafe(self._loop.stop)
        self._thread.join(timeout=5.0)
        self._loop.close()

    def __enter__(self) -> SyncVisionClient:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


async def _make_client(host: str, port: int, kwargs: dict[str, Any]) -> VisionClient:
    # Built inside the loop's thread so its asyncio primitives bind to that loop.
    return VisionClient(host, port, **kwargs)


async def wait_for_server(
    host: str, port: int, *, timeout_s: float = 10.0, **kwargs: Any
) -> Welcome:
    """Connect, retrying until ``timeout_s``: for scripts that start a server and then use it."""
    deadline = time.monotonic() + timeout_s
    while True:
        client = VisionClient(host, port, reconnect=ReconnectPolicy(attempts=0), **kwargs)
        try:
            welcome = await client.connect()
            await client.close()
            return welcome
        except ConnectionLost:
            if time.monotonic() > deadline:
                raise
            await asyncio.sleep(0.05)
