"""The line front-end: short ASCII lines for robot controllers (protocol/LINE.md), as a thin
adapter over :class:`vision_server.service.InspectionService`.

One task per connection reads a line, answers it, and only then reads the next: one trigger
at a time per connection, answers in the order of the lines, as a controller's program that
sends a line and then reads expects. Connections are independent tasks, so a slow, silent or
misbehaving controller holds only its own connection. What is this front-end's own: the
listener (``max_connections``, optional TLS), the token line, the line limits (length, idle
time), the numbers of inspections and the rendering of answers (:mod:`.line_codec`).
"""

from __future__ import annotations

import asyncio
import contextlib
import hmac
import logging
import math
import ssl
import time
from collections.abc import Callable
from dataclasses import dataclass, replace

from protocol import (
    Busy,
    CellvisionError,
    DeadlineExceeded,
    FrameTooLarge,
    InternalError,
    InvalidArgument,
    NotAuthenticated,
    ShuttingDown,
    UnknownInspection,
)

from ..config import LINE_FORMATS, LineSettings, TcpSettings
from ..inspections import (
    RESULT_KINDS,
    Inspection,
    OutputFormat,
    default_output,
    numbers_by_position,
)
from ..service import (
    Catalog,
    InspectionRecord,
    InspectionService,
    InspectReply,
    InspectRequest,
)
from .line_codec import (
    Command,
    error_line,
    ok_line,
    parse_line,
    result_line,
    trigger_error_line,
)
from .line_poses import CONVENTIONS, Matrix, parse_pose, pose_values
from .listener import Clock, Listener, Policy

log = logging.getLogger("vision_server")
FRONTEND = "line protocol"
"""This front-end's name at the service's front door (its counts, its refusals)."""

READ_CHUNK = 4096
TLS_HANDSHAKE_TIMEOUT_S = 10.0


class _Closed(Exception):
    """The connection is over (the peer left, or we end it)."""


@dataclass(frozen=True)
class Answerable:
    """An inspection as a line answers it: its name, the values of its summary it sends."""

    name: str
    type: str
    output: OutputFormat

    def count(self, fmt: str) -> int:
        """Numbers after the verdict in format ``fmt``."""
        return self.output.count(CONVENTIONS[fmt].count)

    def values(
        self, reply: InspectReply, fmt: str, base_from_tool: Matrix | None = None
    ) -> list[tuple[float, int]]:
        """The answer's numbers in format ``fmt``; a base-frame pose of a tool camera needs
        the TCP pose the trigger carried (without it the pose is sent as missing)."""
        kind = RESULT_KINDS.get(self.type)
        summary = {} if kind is None else kind.summary(reply.data)
        base = self.output.base
        if base is None:
            return self.output.values(summary)
        convention = CONVENTIONS[fmt]
        pose = None
        if base_from_tool is not None or not base.needs_tool_pose:
            pose = base.pose(summary.get("u", math.nan), summary.get("v", math.nan), base_from_tool)
        if pose is None:
            numbers = [(math.nan, convention.position_decimals)] * convention.count
        else:
            numbers = pose_values(fmt, pose)
        return self.output.values(summary, numbers)

    def tool_pose(self, fmt: str, words: tuple[str, ...]) -> Matrix | None:
        """The TCP pose a trigger's words after the inspection give (None: none given and
        none needed). Raises INVALID_ARGUMENT for a pose the inspection does not take or a
        missing one it needs."""
        base = self.output.base
        needed = base is not None and base.needs_tool_pose
        if not words:
            if needed:
                assert base is not None
                names = " ".join(["x", "y", "z", *CONVENTIONS[fmt].rotation])
                raise InvalidArgument(
                    f"camera {base.camera!r} of {self.name!r} is on the tool: send the "
                    f"robot's TCP pose, T <inspection> {names}"
                )
            return None
        if not needed:
            raise InvalidArgument(
                f"{self.name!r} takes no pose: its camera is not on the tool with frame: base"
            )
        return parse_pose(fmt, words)


def answerable(inspection: Inspection, catalog: Catalog | None = None) -> Answerable:
    """The output an inspection's ``output:`` declares, else every summary value of its type.
    ``catalog``: where a base-frame output without configured intrinsics finds its camera's
    (a sim camera's come from its scene)."""
    declared = getattr(inspection, "output", None)
    output = (
        declared
        if isinstance(declared, OutputFormat)
        else default_output(RESULT_KINDS.get(inspection.type))
    )
    if output.base is not None and output.base.intrinsics is None and catalog is not None:
        camera = catalog.cameras.get(inspection.camera)
        if camera is not None:
            output = replace(output, base=output.base.with_intrinsics(camera.intrinsics))
    return Answerable(inspection.name, inspection.type, output)


def inspection_numbers(catalog: Catalog) -> dict[int, str]:
    """Each inspection's number (its ``number:``, else its position in the list)."""
    return numbers_by_position(
        (i.name, getattr(i, "number", None)) for i in catalog.inspections.values()
    )


class LineFrontend:
    """Listens for controllers and serves them with ``service``. ``tcp``: the main port's
    settings, whose token (and, with ``settings.tls``, certificate) this port uses too."""

    def __init__(
        self,
        service: InspectionService,
        settings: LineSettings,
        tcp: TcpSettings | None = None,
    ) -> None:
        self.service = service
        self.settings = settings
        self.tcp = tcp or TcpSettings()
        self.sessions: set[LineSession] = set()
        self.latest: dict[str, InspectReply] = {}
        """The newest answered result of each inspection, from any front-end (for ``R name``)."""
        self._listener: Listener | None = None
        self._unsubscribe: Callable[[], None] = lambda: None
        self._stopping = False

    @property
    def port(self) -> int:
        if self._listener is None:
            raise RuntimeError("the line front-end is not started")
        return self._listener.address[1]

    async def start(self) -> None:
        context: ssl.SSLContext | None = self.tcp.ssl_context() if self.settings.tls else None
        # Connections come through the service's front door, counted before TLS; the
        # listener also drops a controller that reads none of its answers, and one that has
        # not signed in within the handshake timeout (vision_server/frontends/listener.py).
        policy = Policy(
            name=FRONTEND,
            max_connections=self.settings.max_connections,
            request_timeout_s=self.tcp.handshake_timeout_s,
            idle_timeout_s=self.settings.idle_timeout_s,
            write_timeout_s=self.settings.write_timeout_s,
            # The TLS handshake is part of signing in: A <token> is due within
            # handshake_timeout_s of connecting, TLS or not.
            tls_handshake_timeout_s=min(TLS_HANDSHAKE_TIMEOUT_S, self.tcp.handshake_timeout_s),
        )
        loop = asyncio.get_running_loop()

        def protocol() -> asyncio.BaseProtocol:
            reader = asyncio.StreamReader(limit=READ_CHUNK * 4, loop=loop)
            return asyncio.StreamReaderProtocol(reader, self._accept, loop=loop)

        self._listener = Listener(
            self.service.door,
            policy,
            protocol,
            ssl_context=context,
            refusal_message=lambda refusal: error_line(Busy(f"{refusal.reason}; try again")),
        )
        await self._listener.start(self.settings.host, self.settings.port)
        self._unsubscribe = self.service.subscribe(self._remember)
        log.info("line protocol listening on %s:%d", self.settings.host, self.port)

    async def stop(self) -> None:
        """Stop accepting; answer what is running (up to the main port's grace period, then
        SHUTTING_DOWN), close every connection."""
        self._stopping = True
        self._unsubscribe()
        if self._listener is not None:
            await self._listener.stop_accepting()
        sessions = list(self.sessions)
        for session in sessions:
            session.stop()
        if sessions:
            await asyncio.wait(
                [asyncio.ensure_future(s.finished.wait()) for s in sessions],
                timeout=self.tcp.shutdown_grace_s,
            )
        for session in sessions:
            session.stop(force=True)  # a trigger past the grace period gets SHUTTING_DOWN
        if self._listener is not None:
            await self._listener.close_connections()

    def _remember(self, record: InspectionRecord) -> None:
        self.latest[record.reply.inspection] = record.reply

    async def _accept(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        """A connection the front door admitted (its count is given back when it closes)."""
        if self._stopping:
            with contextlib.suppress(ConnectionError, OSError):
                writer.write(error_line(ShuttingDown("the server is stopping")))
                async with asyncio.timeout(self.settings.write_timeout_s):
                    await writer.drain()
            writer.transport.abort()
            return
        assert self._listener is not None
        session = LineSession(self, reader, writer, self._listener.clock_of(writer.transport))
        self.sessions.add(session)
        try:
            await session.run()
        finally:
            self.sessions.discard(session)


class LineSession:
    """One controller's connection. See the module."""

    def __init__(
        self,
        frontend: LineFrontend,
        reader: asyncio.StreamReader,
        writer: asyncio.StreamWriter,
        clock: Clock | None = None,
    ) -> None:
        self.frontend = frontend
        self.service = frontend.service
        self.settings = frontend.settings
        self.reader = reader
        self.writer = writer
        self.format = self.settings.format
        self.clock = clock
        """The front door's clock of this connection (its listener's watchdog reads it)."""
        self.authenticated = frontend.tcp.auth_token is None
        connected = clock.started if clock is not None else time.monotonic()
        self.auth_deadline = connected + frontend.tcp.handshake_timeout_s
        """Until it is authenticated, the connection must send ``A <token>`` by then; no
        line before (blank, wrong or too long) moves it."""
        if clock is not None:
            clock.signed_in = self.authenticated
            clock.deadline = math.inf if self.authenticated else self.auth_deadline
        self.last: tuple[Answerable, InspectReply, Matrix | None] | None = None
        """The answer to this connection's last trigger (for ``R``)."""
        self.finished = asyncio.Event()
        self.busy = False
        """A trigger is running: shutdown lets it finish (within the grace period)."""
        self._buffer = bytearray()
        self._discarding = False
        """The rest of a line longer than the limit is being skipped up to its LF."""
        self._task: asyncio.Task[None] | None = None
        peer = writer.get_extra_info("peername")
        self.peer = f"{peer[0]}:{peer[1]}" if isinstance(peer, tuple) else str(peer)

    def stop(self, *, force: bool = False) -> None:
        """End the connection: now when it waits for a line (or ``force``), else after its
        trigger."""
        if self._task is not None and not self._task.done() and (force or not self.busy):
            self._task.cancel()

    async def run(self) -> None:
        self._task = asyncio.current_task()
        try:
            await self._serve()
        except (_Closed, ConnectionError, OSError):
            pass
        except asyncio.CancelledError:
            # Cancelled by stop(): say so if the controller can still hear it.
            with contextlib.suppress(Exception):
                self.writer.write(error_line(ShuttingDown("the server is stopping")))
        finally:
            self.writer.close()
            self.finished.set()

    async def _serve(self) -> None:
        log.info("%s: line protocol connection", self.peer)
        while True:
            if self.frontend._stopping and not self.busy:
                raise _Closed
            raw = await self._next_line()
            if raw is None:  # a line longer than the limit: its start is answered
                limit = self.settings.max_line_bytes
                await self._send(
                    error_line(FrameTooLarge(f"line longer than {limit} bytes; it is skipped"))
                )
                continue
            try:
                command = parse_line(raw)
            except CellvisionError as exc:
                await self._send(error_line(exc))
                continue
            if command is None:
                continue  # a blank line asks nothing
            await self._answer(command)

    # ------------------------------------------------------------------ reading

    async def _next_line(self) -> bytes | None:
        """The next complete line without its LF; None once for a line longer than the
        limit (its rest is skipped up to its LF). Raises _Closed when the peer has gone or
        sent no complete line within the idle timeout (answered with an error line)."""
        limit = self.settings.max_line_bytes
        if self.authenticated:
            deadline = time.monotonic() + self.settings.idle_timeout_s
        else:
            deadline = self.auth_deadline
        while True:
            end = self._buffer.find(b"\n")
            if end >= 0:
                line = bytes(self._buffer[:end])
                del self._buffer[: end + 1]
                if self._discarding:
                    self._discarding = False
                    continue
                if end + 1 > limit:
                    return None
                return line
            if self._discarding:
                self._buffer.clear()
            elif len(self._buffer) >= limit:
                self._buffer.clear()
                self._discarding = True
                return None
            chunk = await self._read(deadline)
            if not chunk:
                raise _Closed
            self._buffer += chunk

    async def _read(self, deadline: float) -> bytes:
        try:
            async with asyncio.timeout(max(deadline - time.monotonic(), 0.0)):
                return await self.reader.read(READ_CHUNK)
        except TimeoutError:
            if not self.authenticated:
                limit = self.frontend.tcp.handshake_timeout_s
                log.info("%s: no A <token> within %g s; closing", self.peer, limit)
                await self._send(
                    error_line(NotAuthenticated(f"no A <token> within {limit:g} s; closing"))
                )
                raise _Closed from None
            idle = self.settings.idle_timeout_s
            log.info("%s: no complete line for %g s; closing", self.peer, idle)
            await self._send(
                error_line(DeadlineExceeded(f"no complete line for {idle:g} s; closing"))
            )
            raise _Closed from None

    async def _send(self, data: bytes) -> None:
        if self.writer.is_closing():
            raise _Closed
        self.writer.write(data)
        try:
            async with asyncio.timeout(self.settings.write_timeout_s):
                await self.writer.drain()
        except TimeoutError:
            log.warning("%s: the controller does not read its answers; dropping it", self.peer)
            # Dropped, not closed: a graceful close would wait for it to read what is queued.
            self.writer.transport.abort()
            raise _Closed from None

    # ------------------------------------------------------------------ commands

    async def _answer(self, command: Command) -> None:
        if command.verb == "A":
            await self._authenticate(command.arg or "")
            return
        if not self.authenticated:
            await self._send(
                error_line(NotAuthenticated("send A <token> first: this server needs a token"))
            )
            raise _Closed
        if command.verb == "T":
            await self._trigger(command.arg or "", command.args[1:])
        elif command.verb == "R":
            await self._last_result(command.arg)
        elif command.verb == "L":
            await self._send(self._listing())
        elif command.verb == "P":
            await self._send(ok_line("PONG"))
        elif command.verb == "F":
            await self._set_format(command.arg or "")
        elif command.verb == "Q":
            await self._send(ok_line("BYE"))
            raise _Closed

    async def _authenticate(self, token: str) -> None:
        expected = self.frontend.tcp.auth_token
        if expected is not None and not hmac.compare_digest(token.encode(), expected.encode()):
            log.info("%s: wrong token on the line protocol", self.peer)
            # The front door slows down guessing: the refusal waits, doubling per failure.
            await asyncio.sleep(self.service.door.auth_failed(self.peer))
            await self._send(error_line(NotAuthenticated("wrong token")))
            raise _Closed
        self.authenticated = True
        if self.clock is not None:  # the session's own idle timeout takes over
            self.clock.signed_in = True
            self.clock.deadline = math.inf
        await self._send(ok_line())

    async def _set_format(self, name: str) -> None:
        wanted = name.lower()
        if wanted not in LINE_FORMATS:
            await self._send(
                error_line(
                    InvalidArgument(f"no format {name!r}; formats: {', '.join(LINE_FORMATS)}")
                )
            )
            return
        self.format = wanted
        await self._send(ok_line(wanted.upper()))

    def _listing(self) -> bytes:
        numbers = inspection_numbers(self.service.catalog)
        entries = [f"{n}={name}" for n, name in sorted(numbers.items())]
        return ok_line(str(len(entries)), *entries)

    def _find(self, key: str) -> Answerable:
        """The inspection a trigger names, by number or by name (UNKNOWN_INSPECTION)."""
        catalog = self.service.catalog
        if key.isdigit():
            numbers = inspection_numbers(catalog)
            name = numbers.get(int(key))
            if name is None:
                shown = ", ".join(str(n) for n in sorted(numbers)) or "none"
                raise UnknownInspection(f"no inspection number {int(key)}; numbers: {shown}")
            key = name
        return answerable(catalog.inspection(key), catalog)

    async def _trigger(self, key: str, pose_words: tuple[str, ...] = ()) -> None:
        arrived = time.monotonic()
        target: Answerable | None = None
        self.busy = True
        try:
            target = self._find(key)
            base_from_tool = target.tool_pose(self.format, pose_words)
            deadline = arrived + self.settings.deadline_s
            # A controller waits for its answer: a trigger waits for a worker slot (within its
            # deadline) rather than being refused at once.
            admission = await self.service.admit_when_free(target.name, deadline=deadline)
            try:
                reply = await self.service.inspect(
                    InspectRequest(
                        target.name,
                        None,
                        arrived=arrived,
                        deadline=deadline,
                        peer=f"line {self.peer}",
                    ),
                    admission=admission,
                )
            finally:
                admission.release()
        except CellvisionError as exc:
            log.info("%s: T %s: %s: %s", self.peer, key, exc.code.name, exc.message)
            fields = None if target is None else target.count(self.format)
            await self._send(trigger_error_line(self.format, exc, fields))
            return
        except Exception as exc:  # a bug in an inspection must not end the connection
            log.exception("%s: T %s failed", self.peer, key)
            fields = None if target is None else target.count(self.format)
            error = InternalError(f"{type(exc).__name__}: {exc}")
            await self._send(trigger_error_line(self.format, error, fields))
            return
        finally:
            self.busy = False
        self.last = (target, reply, base_from_tool)
        values = target.values(reply, self.format, base_from_tool)
        await self._send(result_line(self.format, reply.passed, values))

    async def _last_result(self, key: str | None) -> None:
        target: Answerable | None = None
        base_from_tool: Matrix | None = None
        try:
            if key is None:
                if self.last is None:
                    raise InvalidArgument("no trigger on this connection yet")
                target, reply, base_from_tool = self.last
            else:
                target = self._find(key)
                found = self.frontend.latest.get(target.name)
                if found is None:
                    raise InvalidArgument(f"inspection {target.name!r} has no result yet")
                reply = found
        except CellvisionError as exc:
            fields = None if target is None else target.count(self.format)
            await self._send(trigger_error_line(self.format, exc, fields))
            return
        values = target.values(reply, self.format, base_from_tool)
        await self._send(result_line(self.format, reply.passed, values))


__all__ = ["Answerable", "LineFrontend", "LineSession", "answerable", "inspection_numbers"]
