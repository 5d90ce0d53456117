"""The Modbus front-end against what attackers and testers found (issue 28, "One front door"):
function 23 refused whole or done whole, the shutdown MODBUS.md §3 promises as a PLC sees it,
idle connections closed, clients that do not read their answers dropped, connections beyond
``max_connections`` closed at once, and which exception wins for another unit id.

pymodbus's own client is the PLC where a PLC's requests are meant; raw sockets where a client
misbehaves.
"""

from __future__ import annotations

import asyncio
import contextlib
import socket
import struct
import time
from pathlib import Path

import cv2
import numpy as np
import pytest
from loopback import Gate, run, wait_until
from plc import UNIT, Plc, exchange, mbap

from vision_server import Catalog
from vision_server.app import App
from vision_server.cameras import FolderCamera, FolderCameraSettings
from vision_server.config import ConfigError, ModbusSettings, ServerSettings, load_config
from vision_server.frontends.modbus import WRITE_BUFFER_MAX, ModbusFrontend
from vision_server.frontends.modbus_frames import pdu_problem, read_write
from vision_server.frontends.modbus_handshake import Handshake
from vision_server.frontends.modbus_map import SIZE, Refusal, Reg, Status, build_map

MEAN = 100


def make_app(
    tmp_path: Path, gate: Gate, *, grace_s: float = 5.0, **modbus: object
) -> tuple[App, FolderCamera]:
    """A server whose inspection 1 is ``gate`` (it blocks until the test releases it)."""
    (tmp_path / "imgs").mkdir(exist_ok=True)
    cv2.imwrite(str(tmp_path / "imgs" / "a.png"), np.full((48, 64), MEAN, np.uint8))
    camera = FolderCamera("shelf", FolderCameraSettings(tmp_path / "imgs"))
    camera.open()
    catalog = Catalog.build([camera], [gate])
    settings = ModbusSettings(enabled=True, port=0, **modbus)  # type: ignore[arg-type]
    server = ServerSettings(port=0, workers=2, shutdown_grace_s=grace_s)
    return App(catalog, server, modbus=settings), camera


def frontend(app: App) -> ModbusFrontend:
    assert app.modbus is not None
    return app.modbus


def read_frame(tid: int, address: int, count: int, unit: int = UNIT) -> bytes:
    return mbap(tid, unit, struct.pack(">BHH", 3, address, count))


def read_write_frame(
    read_address: int, read_count: int, write_address: int, values: list[int], unit: int = UNIT
) -> bytes:
    pdu = struct.pack(
        f">BHHHHB{len(values)}H",
        23,
        read_address,
        read_count,
        write_address,
        len(values),
        2 * len(values),
        *values,
    )
    return mbap(1, unit, pdu)


def exception_of(reply: bytes) -> tuple[int, int | None]:
    """A reply frame's function byte and its exception code (None when it is no exception)."""
    function = reply[7]
    return function, (reply[8] if function & 0x80 else None)


async def closed_by_server(reader: asyncio.StreamReader) -> bool:
    """Read until the server ends the connection (answers are skipped); True then."""
    try:
        while await reader.read(65536):
            pass
    except ConnectionResetError:
        pass
    return True


# ----------------------------------------------------------------------------- function 23


def test_read_write_multiple_is_refused_whole_or_done_whole(tmp_path: Path) -> None:
    """A write of CONTROL=1 with a read past the map is exception 0x02 and writes nothing:
    no inspection runs, SEQUENCE does not move. A valid one writes, triggers and reads."""
    gate = Gate(camera="shelf")

    async def body() -> None:
        app, camera = make_app(tmp_path, gate)
        async with app:
            port = frontend(app).port
            plc = await Plc(port).connect()
            client = plc.client
            refused = {
                "CONTROL=1, a read past the map": dict(
                    read_address=SIZE - 1, read_count=2, write_address=Reg.CONTROL, values=[1]
                ),
                "CONTROL=1 and INSPECTION, a read far past the map": dict(
                    read_address=60000, read_count=1, write_address=Reg.CONTROL, values=[1, 1]
                ),
                "a good read, a write of CONTROL..STATUS": dict(
                    read_address=0, read_count=12, write_address=Reg.CONTROL, values=[1, 1, 1]
                ),
            }
            for what, request in refused.items():
                reply = await client.readwrite_registers(**request, device_id=UNIT)  # type: ignore[arg-type]
                assert reply.isError(), what
                assert reply.exception_code == 0x02, f"{what}: {reply}"
            # Counts out of range are 0x03, and write nothing either (raw: the client refuses).
            for what, data in {
                "no register read": read_write_frame(0, 0, Reg.CONTROL, [1]),
                "126 registers read": read_write_frame(0, 126, Reg.CONTROL, [1]),
                "a byte count that is not the write count's": mbap(
                    1, UNIT, struct.pack(">BHHHHBHB", 23, 0, 1, 0, 1, 3, 1, 0)
                ),
            }.items():
                assert exception_of(await exchange(port, data)) == (0x97, 0x03), what
            await asyncio.sleep(0.2)  # a run, had one started, would be in the gate by now
            regs = await plc.read(0, 12)
            assert (regs[Reg.CONTROL], regs[Reg.INSPECTION]) == (0, 0), "nothing was written"
            assert (regs[Reg.STATUS], regs[Reg.SEQUENCE], regs[Reg.REFUSALS]) == (
                Status.READY,
                0,
                0,
            )
            assert gate.entered == 0, "no inspection ran"

            reply = await client.readwrite_registers(
                read_address=0, read_count=12, write_address=Reg.CONTROL, values=[1, 1]
            )
            assert not reply.isError(), reply
            assert reply.registers[Reg.CONTROL] == 1, "the read comes after the write"
            assert reply.registers[Reg.STATUS] == Status.BUSY, "the write triggered"
            await wait_until(lambda: gate.entered == 1, "the inspection runs")
            gate.release.set()
            await plc.wait_status(Status.DONE)
            done = await plc.result()
            assert (done.status, done.sequence, done.inspection) == (
                Status.DONE | Status.PASS,
                1,
                1,
            )
            plc.close()
        camera.close()

    try:
        run(body())
    finally:
        gate.release.set()


# ----------------------------------------------------------------------------- shutdown


def test_at_a_stop_a_plc_sees_ready_clear_and_its_trigger_refused(tmp_path: Path) -> None:
    """While the front-end stops, its connections are still served: READY is clear, a trigger
    edge is refused with 103 and runs nothing; the drain ends once the PLC has gone."""
    gate = Gate(camera="shelf")

    async def body() -> None:
        app, camera = make_app(tmp_path, gate, shutdown_drain_s=20.0)
        await app.start()
        stopping: asyncio.Task[None] | None = None
        try:
            plc = await Plc(frontend(app).port).connect()
            assert await plc.status() == Status.READY
            began = time.monotonic()
            stopping = asyncio.create_task(app.stop())
            await wait_until(lambda: not frontend(app).handshake.accepting, "the stop began")
            assert await plc.status() == Status(0), "READY clears once the stop begins"
            await plc.trigger(1)
            refused = await plc.result()
            assert (refused.status, refused.refusal, refused.refusals, refused.sequence) == (
                Status(0),
                Refusal.NOT_READY,
                1,
                0,
            )
            await asyncio.sleep(0.2)
            assert gate.entered == 0, "the refused edge ran nothing"
            assert not stopping.done(), "the PLC's connection is still served"
            plc.close()
            async with asyncio.timeout(10.0):
                await stopping
            assert time.monotonic() - began < 10.0, "the drain ends once no PLC is left"
        finally:
            if stopping is None:
                await app.stop()
            camera.close()

    try:
        run(body())
    finally:
        gate.release.set()


def test_a_run_in_progress_at_a_stop_ends_in_done_with_error_22(tmp_path: Path) -> None:
    """A run that outlasts the grace period ends in DONE with ERROR and ERROR_CODE 22, and the
    PLC reads it over its connection, which is still served; a trigger edge meanwhile (BUSY)
    is refused with 103, the stop's refusal; acknowledging clears DONE but READY stays clear."""
    gate = Gate(camera="shelf")

    async def body() -> None:
        app, camera = make_app(tmp_path, gate, grace_s=0.3, shutdown_drain_s=20.0)
        await app.start()
        stopping: asyncio.Task[None] | None = None
        try:
            plc = await Plc(frontend(app).port).connect()
            await plc.trigger(1)
            await wait_until(lambda: gate.entered == 1, "the inspection runs")
            stopping = asyncio.create_task(app.stop())
            await wait_until(lambda: not frontend(app).handshake.accepting, "the stop began")
            assert await plc.status() == Status.BUSY
            await plc.write_control(0)
            await plc.write_control(1)  # a new edge while BUSY, during the stop
            busy = await plc.result()
            assert (busy.status, busy.refusal, busy.refusals) == (
                Status.BUSY,
                Refusal.NOT_READY,
                1,
            )
            await plc.wait_status(Status.DONE, timeout_s=10.0)  # after the grace of 0.3 s
            done = await plc.result()
            assert (done.status, done.error_code, done.sequence, done.inspection) == (
                Status.DONE | Status.ERROR,
                22,
                1,
                1,
            )
            gate.release.set()  # the worker thread lets go of the abandoned run
            await plc.write_control(0)  # acknowledge
            assert await plc.status() == Status.ERROR, "DONE clears, READY stays clear"
            assert not stopping.done(), "the PLC's connection is still served"
            plc.close()
            async with asyncio.timeout(10.0):
                await stopping
        finally:
            gate.release.set()
            if stopping is None:
                await app.stop()
            camera.close()

    try:
        run(body())
    finally:
        gate.release.set()


def test_the_drain_at_a_stop_is_bounded(tmp_path: Path) -> None:
    """A connection that stays open holds the stop for ``shutdown_drain_s``, no longer; then
    it is closed."""
    gate = Gate(camera="shelf")

    async def body() -> None:
        app, camera = make_app(tmp_path, gate, shutdown_drain_s=0.5)
        await app.start()
        try:
            reader, writer = await asyncio.open_connection("127.0.0.1", frontend(app).port)
            await wait_until(lambda: len(frontend(app).connections) == 1, "connected")
            began = time.monotonic()
            await app.stop()
            took = time.monotonic() - began
            assert 0.4 <= took < 5.0, f"the stop took {took:.2f} s"
            async with asyncio.timeout(5.0):
                assert await closed_by_server(reader)
            writer.close()
        finally:
            camera.close()

    run(body())


# ----------------------------------------------------------------------------- idle timeout


def test_a_connection_that_is_served_nothing_is_closed_at_the_idle_timeout(
    tmp_path: Path,
) -> None:
    """``idle_timeout_s`` 0.5: a silent connection, one that sends a frame a byte at a time
    (never whole) and one whose requests are all refused are closed after it; one that reads
    every 0.1 s stays open three times as long, then goes silent and is closed too."""
    gate = Gate(camera="shelf")
    idle = 0.5

    async def closed_after(chunks: list[bytes], every_s: float) -> float:
        """Seconds until the server closes a connection that sends ``chunks``, one every
        ``every_s`` (none: a silent connection)."""
        reader, writer = await asyncio.open_connection("127.0.0.1", port)
        began = time.monotonic()

        async def keep_sending() -> None:
            with contextlib.suppress(ConnectionError):
                for chunk in chunks:
                    writer.write(chunk)
                    await writer.drain()
                    await asyncio.sleep(every_s)

        sender = asyncio.create_task(keep_sending())
        try:
            async with asyncio.timeout(10.0):
                await closed_by_server(reader)
            return time.monotonic() - began
        finally:
            sender.cancel()
            writer.close()

    async def served_for(seconds: float) -> float:
        """Read STATUS every 0.1 s for ``seconds``, each answered; then seconds until the
        server closes the connection once it is silent."""
        reader, writer = await asyncio.open_connection("127.0.0.1", port)
        try:
            silent = time.monotonic()
            for tid in range(int(seconds / 0.1)):
                await asyncio.sleep(0.1)
                writer.write(read_frame(tid, Reg.STATUS, 1))
                reply = await reader.readexactly(11)
                silent = time.monotonic()  # the last answer: served up to here
                assert struct.unpack(">H", reply[:2])[0] == tid
            async with asyncio.timeout(10.0):
                await closed_by_server(reader)
            return time.monotonic() - silent
        finally:
            writer.close()

    async def body() -> None:
        nonlocal port
        app, camera = make_app(tmp_path, gate, idle_timeout_s=idle)
        async with app:
            port = frontend(app).port
            # A whole frame of 260 bytes (a write of 123 registers), a byte at a time: 26 s.
            values = struct.pack(">BHHB123H", 16, 0, 123, 246, *([0] * 123))
            drip = [bytes([b]) for b in mbap(1, UNIT, values)]
            refused = [read_frame(tid, 0, 1, unit=9) for tid in range(100)]  # each 0x0B
            silent, partial, refused_for, served = await asyncio.gather(
                closed_after([], 0.0),
                closed_after(drip, 0.1),
                closed_after(refused, 0.1),
                served_for(3 * idle),
            )
            closed = {"silent": silent, "partial": partial, "refused": refused_for}
            for what, took in closed.items():
                assert idle - 0.1 <= took < idle + 2.0, f"{what}: closed after {took:.2f} s"
            assert idle - 0.1 <= served < idle + 2.0, f"served: closed {served:.2f} s after"
        camera.close()

    port = 0
    run(body())


CELL = """\
cameras:
  tool: {source: request}
inspections:
  - {name: bright, type: presence, camera: tool, measure: mean_intensity, min: 10}
modbus: {enabled: true, KEY: VALUE}
"""


def modbus_settings(tmp_path: Path, key: str, value: str) -> ModbusSettings:
    path = tmp_path / "cell.yaml"
    path.write_text(CELL.replace("KEY", key).replace("VALUE", value), encoding="utf-8")
    return load_config(path).modbus


def test_the_timeouts_are_settings_above_zero(tmp_path: Path) -> None:
    for key, default in (("idle_timeout_s", 60.0), ("write_timeout_s", 10.0)):
        assert getattr(ModbusSettings(), key) == default
        for bad in ("0", "-1", "x"):
            with pytest.raises(ConfigError, match=f"modbus -> {key}"):
                modbus_settings(tmp_path, key, bad)
        assert getattr(modbus_settings(tmp_path, key, "2.5"), key) == 2.5
    assert ModbusSettings().shutdown_drain_s == 1.0
    with pytest.raises(ConfigError, match="modbus -> shutdown_drain_s"):
        modbus_settings(tmp_path, "shutdown_drain_s", "-1")
    assert modbus_settings(tmp_path, "shutdown_drain_s", "0").shutdown_drain_s == 0.0


# ----------------------------------------------------------------------------- write timeout


def small_window_socket(port: int) -> socket.socket:
    """A connected socket whose receive buffer is small: what the server writes to a client
    that does not read piles up in the server."""
    sock = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)
    sock.connect(("127.0.0.1", port))
    sock.setblocking(False)
    return sock


def test_a_client_that_does_not_read_its_answers_is_dropped(tmp_path: Path) -> None:
    """``write_timeout_s`` 0.5: a client that keeps sending reads of the whole map and never
    reads an answer (the kernel's socket buffers fill first, then the server's) is dropped,
    holding no more than a bounded buffer meanwhile; a client that reads gets every answer to
    as many; a PLC is served throughout."""
    gate = Gate(camera="shelf")
    flood = b"".join(read_frame(tid, 0, SIZE) for tid in range(1000))

    async def body() -> None:
        app, camera = make_app(tmp_path, gate, write_timeout_s=0.5)
        async with app:
            modbus = frontend(app)
            port = modbus.port
            plc = await Plc(port).connect()
            await wait_until(lambda: len(modbus.connections) == 1, "the PLC is connected")

            reader, writer = await asyncio.open_connection(sock=small_window_socket(port))
            await wait_until(lambda: len(modbus.connections) == 2, "the flood is connected")
            most = 0
            async with asyncio.timeout(20.0):
                while len(modbus.connections) == 2:
                    if writer.transport.get_write_buffer_size() < len(flood):
                        writer.write(flood)  # never read, never drained
                    for connection in modbus.connections:
                        if connection.stream is not None:
                            most = max(most, connection.stream.get_write_buffer_size())
                    assert await plc.status() == Status.READY, "the PLC is served meanwhile"
                    await asyncio.sleep(0.02)
            assert most <= WRITE_BUFFER_MAX, f"{most} bytes held for a client that does not read"
            writer.close()

            reader, writer = await asyncio.open_connection("127.0.0.1", port)
            writer.write(flood * 5)
            answers = 0
            async with asyncio.timeout(20.0):
                while answers < 5000:
                    header = await reader.readexactly(7)
                    await reader.readexactly(struct.unpack(">H", header[4:6])[0] - 1)
                    answers += 1
            writer.close()
            plc.close()
        camera.close()

    run(body(), timeout_s=60.0)


# ----------------------------------------------------------------------------- max_connections


def test_connections_beyond_max_connections_are_closed_at_once(tmp_path: Path) -> None:
    gate = Gate(camera="shelf")

    async def body() -> None:
        app, camera = make_app(tmp_path, gate, max_connections=2)
        async with app:
            modbus = frontend(app)
            port = modbus.port
            held = [await asyncio.open_connection("127.0.0.1", port) for _ in range(2)]
            for tid, (reader, writer) in enumerate(held):
                writer.write(read_frame(tid, Reg.STATUS, 1))
                assert len(await reader.readexactly(11)) == 11
            for _ in range(3):
                began = time.monotonic()
                reader, writer = await asyncio.open_connection("127.0.0.1", port)
                writer.write(read_frame(9, Reg.STATUS, 1))
                async with asyncio.timeout(5.0):
                    assert await closed_by_server(reader)
                assert time.monotonic() - began < 1.0, "closed at once"
                writer.close()
            assert len(modbus.connections) == 2
            for tid, (reader, writer) in enumerate(held):  # the two are served on
                writer.write(read_frame(tid, Reg.STATUS, 1))
                assert len(await reader.readexactly(11)) == 11
            held[0][1].close()
            await wait_until(lambda: len(modbus.connections) == 1, "one is gone")
            reader, writer = await asyncio.open_connection("127.0.0.1", port)
            writer.write(read_frame(5, Reg.STATUS, 1))
            async with asyncio.timeout(5.0):
                assert len(await reader.readexactly(11)) == 11, "its place is free again"
            writer.close()
            held[1][1].close()
        camera.close()

    run(body())


# ----------------------------------------------------------------------------- which exception


def test_a_request_to_another_unit_is_0x0b_whatever_its_pdu(tmp_path: Path) -> None:
    """MODBUS.md §4.3: the unit id is judged first (0x0B, the PDU is the other device's to
    judge), then the function (0x01), then lengths and counts (0x03), then addresses (0x02)."""
    gate = Gate(camera="shelf")
    pdus = {
        "read coils": (bytes([1, 0, 0, 0, 1]), 0x01),
        "an unknown function": (bytes([0x63, 1, 2]), 0x01),
        "no function data": (bytes([0x2B]), 0x01),
        "a read one byte too long": (struct.pack(">BHHB", 3, 0, 1, 0), 0x03),
        "a read of 200 registers": (struct.pack(">BHH", 3, 0, 200), 0x03),
        "a read past the map": (struct.pack(">BHH", 3, SIZE, 1), 0x02),
        "a write of STATUS": (struct.pack(">BHH", 6, Reg.STATUS, 1), 0x02),
        "function 23 past the map": (read_write_frame(SIZE, 1, 0, [1])[7:], 0x02),
    }

    async def body() -> None:
        app, camera = make_app(tmp_path, gate)
        async with app:
            port = frontend(app).port
            for what, (pdu, own) in pdus.items():
                function = (pdu[0] | 0x80) & 0xFF
                for unit in (2, 9, 254):
                    got = exception_of(await exchange(port, mbap(1, unit, pdu)))
                    assert got == (function, 0x0B), f"{what} to unit {unit}: {got}"
                for unit in (UNIT, 0, 255):
                    got = exception_of(await exchange(port, mbap(1, unit, pdu)))
                    assert got == (function, own), f"{what} to unit {unit}: {got}"
            regs = struct.unpack(">12H", (await exchange(port, read_frame(1, 0, 12)))[9:])
            assert (regs[Reg.STATUS], regs[Reg.SEQUENCE], regs[Reg.REFUSALS]) == (
                Status.READY,
                0,
                0,
            )
        camera.close()

    run(body())


# ----------------------------------------------------------------------------- sans-IO parts


def test_during_a_stop_every_trigger_edge_is_refused_not_ready() -> None:
    """Whatever else there is (BUSY, an unacknowledged DONE), nothing runs again: 103."""
    hs = Handshake(build_map([], "high_first"))
    assert hs.write(Reg.CONTROL, [1]) == 0  # a run starts (inspection 0)
    hs.stop_accepting()
    hs.write(Reg.CONTROL, [0])
    assert hs.write(Reg.CONTROL, [1]) is None
    assert (hs.registers[Reg.REFUSAL], hs.status) == (Refusal.NOT_READY, Status.BUSY)
    hs.write(Reg.CONTROL, [0])
    from vision_server.frontends.modbus_handshake import Outcome

    hs.finish(Outcome(0, False, 22, (), 0))
    assert hs.status == Status.DONE | Status.ERROR
    hs.registers[Reg.REFUSAL] = 0
    assert hs.write(Reg.CONTROL, [1]) is None  # a pulsed trigger's edge on DONE
    assert hs.registers[Reg.REFUSAL] == Refusal.NOT_READY
    assert hs.registers[Reg.REFUSALS] == 2
    hs.write(Reg.CONTROL, [2])  # ACK: DONE clears, READY does not come back
    assert hs.status == Status.ERROR


def test_function_23_and_16_counts_are_checked_before_any_address() -> None:
    def rw(read_count: int, write_count: int, byte_count: int, words: int) -> bytes:
        head = struct.pack(">BHHHHB", 23, 0, read_count, 0, write_count, byte_count)
        return head + bytes(2 * words)

    assert pdu_problem(rw(1, 1, 2, 1)) is None
    assert pdu_problem(rw(125, 121, 242, 121)) is None
    for bad in (rw(0, 1, 2, 1), rw(126, 1, 2, 1), rw(1, 0, 0, 0), rw(1, 122, 244, 122)):
        assert pdu_problem(bad) == 0x03
    assert pdu_problem(rw(1, 2, 2, 1)) == 0x03, "a byte count that is not the write count's"
    assert pdu_problem(rw(1, 1, 3, 1) + b"\0") == 0x03, "an odd byte count"
    parsed = read_write(struct.pack(">BHHHHBHH", 23, 4, 5, 0, 2, 4, 1, 7))
    assert (parsed.read_address, parsed.read_count, parsed.write_address) == (4, 5, 0)
    assert parsed.values == (1, 7)
    write16 = struct.pack(">BHHB", 16, 0, 2, 4) + bytes(4)
    assert pdu_problem(write16) is None
    assert pdu_problem(struct.pack(">BHHB", 16, 0, 1, 4) + bytes(4)) == 0x03
    assert pdu_problem(struct.pack(">BHHB", 16, 0, 124, 248) + bytes(248)) == 0x03
