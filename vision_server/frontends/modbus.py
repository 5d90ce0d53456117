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
"""

from __future__ import annotations

import asyncio
import logging
import time
from typing import Any

from pymodbus.constants import ExcCodes
from pymodbus.datastore import ModbusServerContext
from pymodbus.pdu import ModbusPDU
from pymodbus.server import ModbusTcpServer
from pymodbus.server.requesthandler import ServerRequestHandler

from protocol import CellvisionError, DeadlineExceeded, ErrorCode, UnknownInspection

from ..config import ModbusSettings
from ..service import Catalog, InspectionService, InspectReply, InspectRequest
from .line import Answerable
from .modbus_frames import (
    ILLEGAL_VALUE,
    FrameReader,
    FramingError,
    Request,
    exception_frame,
    frame,
    pdu_problem,
)
from .modbus_handshake import Handshake, IllegalAddress, IllegalValue, Outcome
from .modbus_map import POSE_FORMAT, RegisterMap, config_map

log = logging.getLogger("vision_server")

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
WRITE_TIMEOUT_S = 10.0
"""How long an answer may wait for a client that does not read its answers; then it is
dropped (its answers would only pile up in the server's memory)."""
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
        """Refuse new triggers; let a running one finish (up to ``grace_s``, then DONE with
        SHUTTING_DOWN); close the listener and every connection."""
        self.handshake.stop_accepting()
        runs = list(self._runs)
        if runs:
            await asyncio.wait(runs, timeout=grace_s)
        for run in runs:
            run.cancel()
        if runs:
            await asyncio.wait(runs)
        if self._server is not None:
            await self._server.shutdown()  # type: ignore[no-untyped-call]
        for connection in list(self.connections):
            if connection.transport is not None:
                connection.transport.close()

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
        if number is not None:
            target = mapped.inspections.get(number)
            run = asyncio.get_running_loop().create_task(
                self._run(number, None if target is None else target.target, mapped.map_id)
            )
            self._runs.add(run)  # kept (and awaited at stop), never fire-and-forget
            run.add_done_callback(self._runs.discard)
        return None

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
    one task, and ends the connection when its stream is not Modbus TCP."""

    def __init__(self, server: _Server) -> None:
        super().__init__(server, None, None, None)  # type: ignore[no-untyped-call]
        self.owner = server
        self.bank = server.bank
        self.reader = FrameReader()
        self.queue: asyncio.Queue[Request | None] = asyncio.Queue()
        """Requests to answer, in order; None once the client has sent all it will."""
        self.reading_paused = False
        self.can_write = asyncio.Event()
        """Cleared while the transport's write buffer is full (asyncio's flow control)."""
        self.can_write.set()
        self.worker: asyncio.Task[None] | None = None

    def callback_connected(self) -> None:
        connections = self.owner.frontend.connections
        if len(connections) >= self.owner.frontend.settings.max_connections:
            log.info("Modbus: too many connections; one more is closed")
            self.transport.close()
            return
        connections.add(self)
        self.worker = asyncio.get_running_loop().create_task(self._answer_in_order())

    def callback_disconnected(self, exc: Exception | None) -> None:
        self.owner.frontend.connections.discard(self)
        if self.worker is not None:
            self.worker.cancel()

    def datagram_received(self, data: bytes, addr: tuple[str, int] | None) -> None:
        try:
            requests = self.reader.feed(data)
        except FramingError as exc:
            log.info("Modbus: %s; closing the connection", exc)
            self.transport.close()
            return
        for request in requests:
            self.queue.put_nowait(request)
        if self.queue.qsize() >= MAX_PENDING and not self.reading_paused:
            self.transport.pause_reading()  # type: ignore[attr-defined]
            self.reading_paused = True

    def pause_writing(self) -> None:
        self.can_write.clear()

    def resume_writing(self) -> None:
        self.can_write.set()

    def eof_received(self) -> bool:  # type: ignore[override]  # asyncio: bool | None
        """The client sent all it will: answer what it sent, then close (True keeps the
        transport open for those answers)."""
        self.queue.put_nowait(None)
        return True

    async def _answer_in_order(self) -> None:
        while True:
            request = await self.queue.get()
            if request is None:
                if self.transport is not None:
                    self.transport.close()
                return
            if self.reading_paused and self.queue.qsize() <= MAX_PENDING // 2:
                self.reading_paused = False
                if self.transport is not None:
                    self.transport.resume_reading()  # type: ignore[attr-defined]
            reply = await self._answer(request)
            try:
                async with asyncio.timeout(WRITE_TIMEOUT_S):
                    await self.can_write.wait()
            except TimeoutError:
                log.info("Modbus: a client does not read its answers; closing")
                if self.transport is not None:
                    self.transport.abort()  # type: ignore[attr-defined]
                return
            if self.transport is None or self.transport.is_closing():
                return
            self.transport.write(reply)  # type: ignore[attr-defined]

    async def _answer(self, request: Request) -> bytes:
        if (code := pdu_problem(request.pdu)) is not None:
            return exception_frame(request, code)
        pdu = self.owner.decoder.decode(request.pdu)
        if pdu is None:  # pymodbus could not decode it
            return exception_frame(request, ILLEGAL_VALUE)
        try:
            response: ModbusPDU = await pdu.datastore_update(self.bank, request.unit)
        except Exception:  # a bug must cost this request, not the connection
            log.exception("Modbus: function %d failed", request.function)
            return exception_frame(request, DEVICE_FAILURE)
        body = response.function_code.to_bytes(1, "big") + response.encode()
        return frame(request.transaction, request.unit, body)


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
