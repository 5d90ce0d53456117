"""The Modbus TCP front-end: PLCs run inspections through a register hand-shake
(protocol/MODBUS.md), a thin adapter over :class:`vision_server.service.InspectionService`.

pymodbus (the optional extra ``modbus``) listens, decodes and executes the register requests;
the front-end frames them itself (:mod:`.modbus_frames`: pymodbus's server framing does not
survive hostile or pipelined input) and answers them in order, one connection at a time; its
data store is replaced by :class:`_Bank`, which hands every read and write to the hand-shake
state machine (:mod:`.modbus_handshake`) on the event loop. A trigger it accepts runs as a task
through the service, with the same admission, deadline and result log as any other request;
its outcome is published in one step. The register map follows the catalog the service
serves: a reload that changes it is picked up at the next request.

A connection is closed when it sends nothing the device serves for ``idle_timeout_s``, and
dropped when it takes none of its answers for ``write_timeout_s``; at a stop the front-end
keeps MODBUS.md §3's promises (READY clear, trigger edges refused, a run in progress ended in
DONE with SHUTTING_DOWN) while it still serves the open connections for a bounded drain, so
that a PLC can read them.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import struct
import time
from typing import Any, cast

from pymodbus.constants import ExcCodes
from pymodbus.datastore import ModbusServerContext
from pymodbus.pdu import ModbusPDU
from pymodbus.server import ModbusTcpServer
from pymodbus.server.requesthandler import ServerRequestHandler

from protocol import CellvisionError, DeadlineExceeded, ErrorCode, UnknownInspection

from ..config import ModbusSettings
from ..service import (
    Catalog,
    InspectionService,
    InspectReply,
    InspectRequest,
    Pass,
    Refusal,
    peer_name,
)
from .line import Answerable
from .modbus_frames import (
    GATEWAY_NO_RESPONSE,
    ILLEGAL_VALUE,
    FrameReader,
    FramingError,
    ReadWrite,
    Request,
    exception_frame,
    frame,
    pdu_problem,
    read_write,
)
from .modbus_handshake import Handshake, IllegalAddress, IllegalValue, Outcome
from .modbus_map import POSE_FORMAT, RegisterMap, config_map

log = logging.getLogger("vision_server")
FRONTEND = "Modbus"
"""This front-end's name at the service's front door (its counts, its refusals)."""

READ_WRITE = 23
"""Read/write multiple registers: answered by :meth:`ModbusFrontend.read_write` as one step
(pymodbus's own does the write before it looks at the read)."""
READ_FUNCTIONS = frozenset({3, 4, 6, 22, 23})
"""Read holding registers, read input registers (the same bank), and the read-back pymodbus
does for write single register, mask write register and read/write multiple registers."""
WRITE_FUNCTIONS = frozenset({6, 16, 22, 23})
"""Write single register, write multiple registers, mask write register, read/write multiple.
Coils and discrete inputs (1, 2, 5, 15) are not served: ILLEGAL FUNCTION."""
THIS_DEVICE = frozenset({0, 255})
"""Unit identifiers that mean "the device at this address" on Modbus TCP."""
MAX_PENDING = 32
"""Requests one connection may have waiting for their answers before the server stops
reading from it (until it has answered half of them): a client that floods holds no more than
this and one read's worth."""
WRITE_BUFFER_HIGH = 16 * 1024
"""Bytes of answers the server holds for a client (beyond the kernel's socket buffer) before
it stops answering it (asyncio's flow control, ``pause_writing``): about 60 answers of a
whole map. A client that takes none of them for ``write_timeout_s`` is dropped."""
WRITE_BUFFER_MAX = 4 * WRITE_BUFFER_HIGH
"""Bytes of answers past which a client is dropped at once (answers wait for the buffer to
drain below WRITE_BUFFER_HIGH, so only a flow-control failure gets here)."""
DEVICE_FAILURE = 0x04
BACKSTOP_S = 1.0
"""How long past its deadline a run may go before the front-end ends it itself: the service
answers DEADLINE_EXCEEDED at the deadline, this only guards BUSY against a stage that would
not (BUSY must never stay set)."""


def catalog_map(catalog: Catalog, word_order: str) -> RegisterMap:
    """The register map of the inspections ``catalog`` serves (in its configuration order)."""
    return config_map(catalog.inspections.values(), word_order, catalog)


class ModbusFrontend:
    """Serves PLCs with ``service`` on ``settings.host``:``settings.port``. See the module."""

    def __init__(self, service: InspectionService, settings: ModbusSettings) -> None:
        self.service = service
        self.settings = settings
        self._catalog = service.catalog
        self.handshake = Handshake(catalog_map(self._catalog, settings.word_order))
        self._runs: set[asyncio.Task[None]] = set()
        self._server: _Server | None = None
        self.connections: set[_Connection] = set()
        self.connections_changed = asyncio.Event()
        """Set when a connection ends (the drain at a stop waits for none to be left)."""

    @property
    def port(self) -> int:
        # pymodbus keeps asyncio's listening Server in ``transport`` (typed as a transport).
        listener: object = None if self._server is None else self._server.transport
        if not isinstance(listener, asyncio.Server) or not listener.sockets:
            raise RuntimeError("the Modbus front-end is not started")
        return int(listener.sockets[0].getsockname()[1])

    async def start(self) -> None:
        if not log.isEnabledFor(logging.INFO):
            # pymodbus logs each malformed frame from a peer as an error, with a hex dump: a
            # hostile or broken client must not fill the server's log (-v shows them).
            logging.getLogger("pymodbus").setLevel(logging.CRITICAL)
        server = _Server(self, address=(self.settings.host, self.settings.port))
        if not await server.listen():
            # The server's message adds the front-end and its address to the cause.
            raise server.listen_error or OSError("pymodbus could not listen")
        self._server = server
        log.info("Modbus TCP listening on %s:%d", self.settings.host, self.port)

    async def stop(self, grace_s: float = 5.0) -> None:
        """Stop as protocol/MODBUS.md §3 promises, serving every connection meanwhile: READY
        clears and every trigger edge is refused (NOT_READY) from now on; a run in progress
        has ``grace_s`` to finish, then ends in DONE with ERROR and SHUTTING_DOWN; then the
        connections are served ``settings.shutdown_drain_s`` more (less once none is left
        open), so that a PLC reads that final state; then the listener and every connection
        close."""
        self.handshake.stop_accepting()
        runs = list(self._runs)
        if runs:
            log.info("Modbus: stopping; a run in progress has %g s to finish", grace_s)
            await asyncio.wait(runs, timeout=grace_s)
        for run in runs:
            run.cancel()
        if runs:
            await asyncio.wait(runs)
        if self._server is not None:
            await self._drain()
        for connection in list(self.connections):
            connection.close_gently()
        if self._server is not None:
            await self._server.shutdown()  # type: ignore[no-untyped-call]

    async def _drain(self) -> None:
        """Serve the open connections (READY clear, edges refused, a last result DONE) until
        none is left or ``shutdown_drain_s`` has passed."""
        with contextlib.suppress(TimeoutError):
            async with asyncio.timeout(self.settings.shutdown_drain_s):
                while self.connections:
                    self.connections_changed.clear()
                    await self.connections_changed.wait()

    # ------------------------------------------------------------------ requests

    def current_map(self) -> RegisterMap:
        """The map of the catalog served now (rebuilt once after each reload)."""
        catalog = self.service.catalog
        if catalog is not self._catalog:
            self._catalog = catalog
            self.handshake.set_map(catalog_map(catalog, self.settings.word_order))
            log.info("Modbus register map regenerated (map id %d)", self.handshake.map.map_id)
        return self.handshake.map

    def serves(self, unit: int) -> bool:
        return unit == self.settings.unit_id or unit in THIS_DEVICE

    def read(self, unit: int, function: int, address: int, count: int) -> list[int] | ExcCodes:
        if not self.serves(unit):
            # What a Modbus TCP gateway answers for a unit behind it that is not there.
            return ExcCodes.GATEWAY_NO_RESPONSE
        if function not in READ_FUNCTIONS:
            return ExcCodes.ILLEGAL_FUNCTION
        self.current_map()
        try:
            return self.handshake.read(address, count)
        except IllegalAddress:
            return ExcCodes.ILLEGAL_ADDRESS
        except IllegalValue:
            return ExcCodes.ILLEGAL_VALUE

    def write(self, unit: int, function: int, address: int, values: list[int]) -> ExcCodes | None:
        if not self.serves(unit):
            return ExcCodes.GATEWAY_NO_RESPONSE
        if function not in WRITE_FUNCTIONS:
            return ExcCodes.ILLEGAL_FUNCTION
        mapped = self.current_map()
        try:
            number = self.handshake.write(address, values)
        except IllegalAddress:
            return ExcCodes.ILLEGAL_ADDRESS
        except IllegalValue:
            return ExcCodes.ILLEGAL_VALUE
        if number is not None:
            target = mapped.inspections.get(number)
            run = asyncio.get_running_loop().create_task(
                self._run(number, None if target is None else target.target, mapped.map_id)
            )
            self._runs.add(run)  # kept (and awaited at stop), never fire-and-forget
            run.add_done_callback(self._runs.discard)
        return None

    def read_write(self, unit: int, request: ReadWrite) -> list[int] | ExcCodes:
        """Function 23 as one step: its read and its write are both checked before anything
        is done, so that a refused request writes nothing and triggers nothing; then the
        write (which may trigger), then the read (which sees it)."""
        if not self.serves(unit):
            return ExcCodes.GATEWAY_NO_RESPONSE
        self.current_map()
        try:
            self.handshake.check_read(request.read_address, request.read_count)
            self.handshake.check_write(request.write_address, request.values)
        except IllegalAddress:
            return ExcCodes.ILLEGAL_ADDRESS
        except IllegalValue:
            return ExcCodes.ILLEGAL_VALUE
        refused = self.write(unit, READ_WRITE, request.write_address, list(request.values))
        if refused is not None:
            return refused
        return self.read(unit, READ_WRITE, request.read_address, request.read_count)

    async def _run(self, number: int, target: Answerable | None, map_id: int) -> None:
        """One accepted trigger, to its DONE (whatever happens: never a stuck BUSY)."""
        arrived = time.monotonic()
        error: ErrorCode | None = None
        passed = False
        values: tuple[float, ...] = ()
        try:
            if target is None:
                known = ", ".join(str(n) for n in sorted(self.handshake.map.inspections))
                raise UnknownInspection(f"no inspection number {number}; numbers: {known}")
            deadline = arrived + self.settings.deadline_s
            try:
                async with asyncio.timeout(self.settings.deadline_s + BACKSTOP_S):
                    reply = await self._inspect(target, arrived, deadline)
            except TimeoutError:
                raise DeadlineExceeded(
                    f"not done within the deadline of {self.settings.deadline_s:g} s"
                ) from None
            passed = reply.passed
            values = tuple(round(v, places) for v, places in target.values(reply, POSE_FORMAT))
        except CellvisionError as exc:
            log.info("Modbus trigger %d: %s: %s", number, exc.code.name, exc.message)
            error = exc.code
        except asyncio.CancelledError:
            self.handshake.finish(Outcome(number, False, int(ErrorCode.SHUTTING_DOWN), (), map_id))
            raise
        except Exception:  # a bug in an inspection must not leave BUSY set
            log.exception("Modbus trigger %d failed", number)
            error = ErrorCode.INTERNAL_ERROR
        self.handshake.finish(
            Outcome(number, passed, 0 if error is None else int(error), values, map_id)
        )

    async def _inspect(self, target: Answerable, arrived: float, deadline: float) -> InspectReply:
        # A PLC waits for DONE: a trigger waits for a worker slot (within its deadline)
        # rather than being refused at once.
        admission = await self.service.admit_when_free(target.name, deadline=deadline)
        try:
            return await self.service.inspect(
                InspectRequest(
                    target.name, None, arrived=arrived, deadline=deadline, peer="modbus"
                ),
                admission=admission,
            )
        finally:
            admission.release()


class _Server(ModbusTcpServer):
    """pymodbus's listener, with connections of ours."""

    def __init__(self, frontend: ModbusFrontend, *, address: tuple[str, int]) -> None:
        self.bank = _Bank(frontend)
        super().__init__(self.bank, address=address)
        self.frontend = frontend
        self.listen_error: OSError | None = None
        """Why listening failed: pymodbus's listen() only logs it and returns False."""
        create = self.call_create

        async def create_keeping_the_error() -> Any:
            try:
                return await create()
            except OSError as exc:
                self.listen_error = exc
                raise

        self.call_create = create_keeping_the_error

    def callback_new_connection(self) -> _Connection:
        return _Connection(self)


class _Connection(ServerRequestHandler):
    """One client: frames its bytes (:class:`FrameReader`), answers its requests in order on
    one task, and ends the connection when its stream is not Modbus TCP, when it sends nothing
    the device serves for ``idle_timeout_s``, or when it takes none of its answers for
    ``write_timeout_s``."""

    def __init__(self, server: _Server) -> None:
        super().__init__(server, None, None, None)  # type: ignore[no-untyped-call]
        self.owner = server
        self.bank = server.bank
        self.settings = server.frontend.settings
        self.reader = FrameReader()
        self.queue: asyncio.Queue[Request | None] = asyncio.Queue()
        """Requests to answer, in order; None once the client has sent all it will."""
        self.reading_paused = False
        self.can_write = asyncio.Event()
        """Cleared while the transport's write buffer is full (asyncio's flow control)."""
        self.can_write.set()
        self.worker: asyncio.Task[None] | None = None
        self.served_at = 0.0
        """When (the loop's clock) the device last served a request of this connection: a
        whole frame answered without a Modbus exception. Nothing else keeps it open."""
        self._idle_timer: asyncio.TimerHandle | None = None
        self._write_timer: asyncio.TimerHandle | None = None
        self.admitted: Pass | None = None
        """This connection's place at the front door, given back when it ends."""

    @property
    def stream(self) -> asyncio.Transport | None:
        """The connection's transport (pymodbus types it as a BaseTransport, and sets it to
        None when it closes the connection itself)."""
        return cast("asyncio.Transport | None", self.transport)

    def callback_connected(self) -> None:
        stream = self.stream
        assert stream is not None
        frontend = self.owner.frontend
        peer = peer_name(stream.get_extra_info("peername"))
        # The service's front door counts it with every front-end's connections (Modbus has
        # no TLS: this is as early as a connection can be counted).
        admitted = frontend.service.door.enter(FRONTEND, peer, limit=self.settings.max_connections)
        if isinstance(admitted, Refusal):
            log.info("Modbus: %s; one more is closed", admitted.reason)
            stream.abort()  # at once: nothing was said on it, nothing is owed
            return
        self.admitted = admitted
        frontend.connections.add(self)
        stream.set_write_buffer_limits(high=WRITE_BUFFER_HIGH)
        self.served_at = self.loop.time()
        self._idle_timer = self.loop.call_later(self.settings.idle_timeout_s, self._check_idle)
        self.worker = self.loop.create_task(self._answer_in_order())

    def callback_disconnected(self, exc: Exception | None) -> None:
        if self.admitted is not None:
            self.admitted.leave()
        frontend = self.owner.frontend
        if self in frontend.connections:
            frontend.connections.discard(self)
            frontend.connections_changed.set()
        if self.worker is not None:
            self.worker.cancel()
        for timer in (self._idle_timer, self._write_timer):
            if timer is not None:
                timer.cancel()

    def close_gently(self) -> None:
        """Close after the answers already written; a client that does not take them within
        ``write_timeout_s`` is aborted."""
        stream = self.stream
        if stream is None or stream.is_closing():
            return
        stream.close()
        if stream.get_write_buffer_size():
            self.loop.call_later(self.settings.write_timeout_s, stream.abort)

    def _check_idle(self) -> None:
        self._idle_timer = None
        stream = self.stream
        if stream is None or stream.is_closing():
            return
        left = self.served_at + self.settings.idle_timeout_s - self.loop.time()
        if left > 0:
            self._idle_timer = self.loop.call_later(left, self._check_idle)
            return
        log.info(
            "Modbus: a connection sent no request served for %g s; closing",
            self.settings.idle_timeout_s,
        )
        self.close_gently()

    def datagram_received(self, data: bytes, addr: tuple[str, int] | None) -> None:
        try:
            requests = self.reader.feed(data)
        except FramingError as exc:
            log.info("Modbus: %s; closing the connection", exc)
            self.close_gently()
            return
        for request in requests:
            self.queue.put_nowait(request)
        if self.queue.qsize() >= MAX_PENDING and not self.reading_paused and self.stream:
            self.stream.pause_reading()
            self.reading_paused = True

    def pause_writing(self) -> None:
        """The write buffer is full: answer nothing more until it drains, and drop the client
        if it takes none of its answers for ``write_timeout_s``."""
        self.can_write.clear()
        if self._write_timer is None:
            self._write_timer = self.loop.call_later(
                self.settings.write_timeout_s, self._write_timed_out
            )

    def resume_writing(self) -> None:
        self.can_write.set()
        if self._write_timer is not None:
            self._write_timer.cancel()
            self._write_timer = None

    def _write_timed_out(self) -> None:
        self._write_timer = None
        log.info(
            "Modbus: a client took none of its answers for %g s; dropping it",
            self.settings.write_timeout_s,
        )
        if self.stream is not None:
            self.stream.abort()

    def eof_received(self) -> bool:  # type: ignore[override]  # asyncio: bool | None
        """The client sent all it will: answer what it sent, then close (True keeps the
        transport open for those answers)."""
        self.queue.put_nowait(None)
        return True

    async def _answer_in_order(self) -> None:
        while True:
            request = await self.queue.get()
            if request is None:
                self.close_gently()
                return
            if self.reading_paused and self.queue.qsize() <= MAX_PENDING // 2:
                self.reading_paused = False
                if self.stream is not None:
                    self.stream.resume_reading()
            reply = await self._answer(request)
            await self.can_write.wait()  # pause_writing's timer drops a client that never reads
            stream = self.stream
            if stream is None or stream.is_closing():
                return
            stream.write(reply)
            if stream.get_write_buffer_size() > WRITE_BUFFER_MAX:
                log.info("Modbus: a client's answers pile up; dropping it")
                stream.abort()
                return

    async def _answer(self, request: Request) -> bytes:
        """The reply frame to ``request``. Which exception wins (protocol/MODBUS.md §4.3): a
        unit id this device is not (0x0B, whatever the PDU), then the function (0x01), then
        the PDU's length and counts (0x03), then the addresses (0x02)."""
        if not self.owner.frontend.serves(request.unit):
            return exception_frame(request, GATEWAY_NO_RESPONSE)
        if (code := pdu_problem(request.pdu)) is not None:
            return exception_frame(request, code)
        try:
            body = await self._execute(request)
        except Exception:  # a bug must cost this request, not the connection
            log.exception("Modbus: function %d failed", request.function)
            return exception_frame(request, DEVICE_FAILURE)
        if body is None:  # pymodbus could not decode it
            return exception_frame(request, ILLEGAL_VALUE)
        if not body[0] & 0x80:
            self.served_at = self.loop.time()
        return frame(request.transaction, request.unit, body)

    async def _execute(self, request: Request) -> bytes | None:
        """The reply PDU (an exception's too), None when pymodbus cannot decode the request."""
        if request.function == READ_WRITE:
            registers = self.owner.frontend.read_write(request.unit, read_write(request.pdu))
            if isinstance(registers, ExcCodes):
                return bytes([READ_WRITE | 0x80, registers])
            words = struct.pack(f">{len(registers)}H", *registers)
            return bytes([READ_WRITE, len(words)]) + words
        pdu = self.owner.decoder.decode(request.pdu)
        if pdu is None:
            return None
        response: ModbusPDU = await pdu.datastore_update(self.bank, request.unit)
        return response.function_code.to_bytes(1, "big") + response.encode()


class _Bank(ModbusServerContext):
    """pymodbus's data store, replaced: every request goes to the front-end."""

    def __init__(self, frontend: ModbusFrontend) -> None:
        # Not the base class's initialiser: it builds a simulated device we do not use. These
        # two attributes make pymodbus call this object itself for every request.
        self.old_simulator = True
        self.simdevices = []
        self._frontend = frontend

    async def async_getValues(  # noqa: N802 (pymodbus's name)
        self, device_id: int, func_code: int, address: int, count: int = 1
    ) -> list[int] | list[bool] | ExcCodes:
        return self._frontend.read(device_id, func_code, address, count)

    async def async_setValues(  # noqa: N802 (pymodbus's name)
        self, device_id: int, func_code: int, address: int, values: list[int] | list[bool]
    ) -> ExcCodes | None:
        return self._frontend.write(device_id, func_code, address, [int(v) for v in values])

    def device_ids(self) -> list[int]:
        return sorted({self._frontend.settings.unit_id, *THIS_DEVICE})


__all__ = ["ModbusFrontend", "catalog_map"]
