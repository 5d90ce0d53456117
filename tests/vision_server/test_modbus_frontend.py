"""Modbus TCP (protocol/MODBUS.md) end to end: pymodbus's client as the PLC against a real
server on loopback port 0. The hand-shake with real inspections, a trigger while busy, a PLC
that never acknowledges, deadlines, a reload that changes the map, Modbus exceptions for bad
requests, and the map ``vision-server modbus-map`` prints being the one served."""

from __future__ import annotations

import asyncio
import contextlib
import io
import json
import os
import re
import signal
import struct
import subprocess
import sys
import time
from collections.abc import AsyncIterator
from pathlib import Path

import cv2
import numpy as np
import pytest
from loopback import Gate, run, wait_until
from plc import Plc, exchange, mbap

from vision_server import Catalog
from vision_server.app import App
from vision_server.cameras import FolderCamera, FolderCameraSettings
from vision_server.commands import main as cli_main
from vision_server.config import ConfigError, ModbusSettings, ServerSettings, load_config
from vision_server.frontends.modbus_map import SIZE, Refusal, Reg, Status
from vision_server.service import CellRuntime

CONFIG = """\
server: {port: 0}
results: {enabled: false}
cameras:
  shelf: {source: folder, path: imgs}
inspections:
  - name: bright
    type: presence
    camera: shelf
    measure: mean_intensity
    min: 10
    output: {decimals: 2}
  - name: dark
    type: presence
    camera: shelf
    measure: mean_intensity
    max: 10
    number: 7
modbus: {enabled: true, port: 0, word_order: WORD_ORDER}
"""
MEAN = 100.0
"""The grey level of the replayed image: ``bright`` passes, ``dark`` fails."""


def write_cell(tmp_path: Path, config: str) -> Path:
    (tmp_path / "imgs").mkdir(exist_ok=True)
    cv2.imwrite(str(tmp_path / "imgs" / "a.png"), np.full((48, 64), int(MEAN), np.uint8))
    path = tmp_path / "cell.yaml"
    path.write_text(config, encoding="utf-8")
    return path


@contextlib.asynccontextmanager
async def serving(path: Path) -> AsyncIterator[App]:
    runtime = CellRuntime(path)
    app = App(
        runtime.catalog,
        ServerSettings(port=0, workers=2),
        reloader=runtime.reload,
        modbus=runtime.config.modbus,
    )
    try:
        async with app:
            yield app
    finally:
        runtime.close()


def modbus_port(app: App) -> int:
    assert app.modbus is not None
    return app.modbus.port


def printed_map(path: Path) -> dict[str, object]:
    """What ``vision-server modbus-map FILE --json`` prints."""
    out = io.StringIO()
    with contextlib.redirect_stdout(out):
        assert cli_main(["modbus-map", str(path), "--json"]) == 0
    parsed: dict[str, object] = json.loads(out.getvalue())
    return parsed


@pytest.mark.parametrize("word_order", ["high_first", "low_first"])
def test_the_full_hand_shake_with_real_inspections(tmp_path: Path, word_order: str) -> None:
    path = write_cell(tmp_path, CONFIG.replace("WORD_ORDER", word_order))
    printed = printed_map(path)

    async def body() -> None:
        async with serving(path) as app:
            plc = await Plc(modbus_port(app), word_order).connect()
            assert await plc.status() == Status.READY
            fixed = await plc.read(Reg.MAP_ID, 3)
            assert fixed[0] == printed["map_id"], "the served map is the one the CLI prints"
            assert fixed[2] == (0 if word_order == "high_first" else 1)

            first = await plc.run(1)
            assert first.status == Status.DONE | Status.PASS
            assert (first.error_code, first.sequence, first.inspection) == (0, 1, 1)
            assert first.values == [MEAN]
            assert first.result_map_id == first.map_id
            # Acknowledged: DONE went, the result stays readable until the next trigger.
            after = await plc.result()
            assert after.status == Status.READY | Status.PASS
            assert after.values == [MEAN]

            second = await plc.run(7)
            assert second.status == Status.DONE  # dark fails: no PASS, no ERROR
            assert (second.error_code, second.sequence, second.inspection) == (0, 2, 7)
            assert second.values == [MEAN]

            unknown = await plc.run(99)
            assert unknown.status == Status.DONE | Status.ERROR
            assert (unknown.error_code, unknown.sequence, unknown.values) == (10, 3, [])
            plc.close()

    run(body())


def test_acknowledge_with_the_ack_bit_after_a_pulsed_trigger(tmp_path: Path) -> None:
    """A PLC that pulses TRIGGER and acknowledges with ACK (bit 1)."""
    path = write_cell(tmp_path, CONFIG.replace("WORD_ORDER", "high_first"))

    async def body() -> None:
        async with serving(path) as app:
            plc = await Plc(modbus_port(app)).connect()
            await plc.trigger(1)
            await plc.wait_status(Status.DONE)
            # TRIGGER stays set (a PLC writes its control word every scan: a repeated level
            # changes nothing), and ACK acknowledges.
            await plc.write_control(1)
            assert Status.DONE in await plc.status()
            await plc.write_control(1 | 2)  # ACK rises
            assert await plc.status() == Status.READY | Status.PASS
            plc.close()

    run(body())


def gate_app(tmp_path: Path, gate: Gate, **modbus: object) -> tuple[App, FolderCamera]:
    (tmp_path / "imgs").mkdir(exist_ok=True)
    cv2.imwrite(str(tmp_path / "imgs" / "a.png"), np.full((48, 64), int(MEAN), np.uint8))
    camera = FolderCamera("shelf", FolderCameraSettings(tmp_path / "imgs"))
    camera.open()
    catalog = Catalog.build([camera], [gate])
    settings = ModbusSettings(enabled=True, port=0, **modbus)  # type: ignore[arg-type]
    return App(catalog, ServerSettings(port=0, workers=2), modbus=settings), camera


def test_a_trigger_while_busy_is_refused_and_the_run_goes_on(tmp_path: Path) -> None:
    gate = Gate(camera="shelf")

    async def body() -> None:
        app, camera = gate_app(tmp_path, gate)
        async with app:
            plc = await Plc(modbus_port(app)).connect()
            await plc.trigger(1)
            await wait_until(lambda: gate.entered == 1, "the inspection runs")
            assert await plc.status() == Status.BUSY
            await plc.write_control(1)  # a PLC that writes its control word every scan
            await plc.write_control(0)
            await plc.write_control(1)  # a new edge while BUSY
            busy = await plc.result()
            assert busy.status == Status.BUSY
            assert (busy.refusal, busy.refusals) == (Refusal.TRIGGER_WHILE_BUSY, 1)
            gate.release.set()
            await plc.wait_status(Status.DONE)
            done = await plc.result()
            assert done.status == Status.DONE | Status.PASS
            assert done.sequence == 1
            assert gate.entered == 1, "the refused edge started nothing"
            plc.close()
        camera.close()

    try:
        run(body())
    finally:
        gate.release.set()


def test_a_plc_that_never_acknowledges_gets_its_next_trigger_refused(tmp_path: Path) -> None:
    """A pulsed trigger whose result is never acknowledged: the next edge is refused with
    NOT_ACKNOWLEDGED and the unread result stays; acknowledging lets the next one run."""
    gate = Gate(camera="shelf")

    async def body() -> None:
        app, camera = gate_app(tmp_path, gate)
        async with app:
            plc = await Plc(modbus_port(app)).connect()
            await plc.trigger(1)
            await wait_until(lambda: gate.entered == 1, "the inspection runs")
            await plc.write_control(0)  # the pulse ends while BUSY: no acknowledgement
            gate.release.set()
            await plc.wait_status(Status.DONE)
            for _ in range(3):  # the edge, then the same level as every scan writes it
                await plc.write_control(1)
            refused = await plc.result()
            assert refused.status == Status.DONE | Status.PASS, "the result is still there"
            assert refused.sequence == 1
            assert (refused.refusal, refused.refusals) == (Refusal.NOT_ACKNOWLEDGED, 1)
            assert gate.entered == 1
            await plc.write_control(2)  # ACK (and TRIGGER falls): acknowledged
            assert await plc.status() == Status.READY | Status.PASS
            await plc.write_control(0)
            again = await plc.run(1)
            assert (again.status, again.sequence, again.refusal) == (
                Status.DONE | Status.PASS,
                2,
                Refusal.NONE,
            )
            assert gate.entered == 2
            plc.close()
        camera.close()

    try:
        run(body())
    finally:
        gate.release.set()


def test_a_deadline_ends_in_done_with_an_error_never_a_stuck_busy(tmp_path: Path) -> None:
    gate = Gate(camera="shelf")

    async def body() -> None:
        app, camera = gate_app(tmp_path, gate, deadline_s=0.2)
        async with app:
            plc = await Plc(modbus_port(app)).connect()
            result = await plc.run(1)  # the gate is never released in time
            assert result.status == Status.DONE | Status.ERROR
            assert result.error_code == 21
            plc.close()
        camera.close()

    try:
        run(body())
    finally:
        gate.release.set()


RELOADED = """\
server: {port: 0}
results: {enabled: false}
cameras:
  shelf: {source: folder, path: imgs}
inspections:
  - name: dark
    type: presence
    camera: shelf
    measure: mean_intensity
    max: 10
    number: 7
  - name: brighter
    type: presence
    camera: shelf
    measure: mean_intensity
    min: 10
    number: 3
    output: {fields: [{name: value, scale: 2}], missing: -1}
modbus: {enabled: true, port: 0}
"""


def test_a_reload_that_changes_the_map_is_served_at_once(tmp_path: Path) -> None:
    path = write_cell(tmp_path, CONFIG.replace("WORD_ORDER", "high_first"))
    before = printed_map(path)

    async def body() -> None:
        async with serving(path) as app:
            plc = await Plc(modbus_port(app)).connect()
            old = await plc.run(1)
            assert old.values == [MEAN]
            path.write_text(RELOADED, encoding="utf-8")
            after = printed_map(path)
            assert after["map_id"] != before["map_id"]
            await app.reload()
            assert (await plc.read(Reg.MAP_ID, 1))[0] == after["map_id"]
            gone = await plc.run(1)  # number 1 is no more
            assert (gone.status, gone.error_code) == (Status.DONE | Status.ERROR, 10)
            new = await plc.run(3)
            assert new.status == Status.DONE | Status.PASS
            assert new.values == [2 * MEAN], "the new output's scale"
            assert new.result_map_id == after["map_id"]
            plc.close()

    run(body())


def test_a_run_in_flight_over_a_reload_finishes_in_the_map_it_started_with(
    tmp_path: Path,
) -> None:
    gate = Gate(camera="shelf")

    async def body() -> None:
        app, camera = gate_app(tmp_path, gate)
        from vision_server.service.builtin import MeanIntensityPresence

        replacement = Catalog.build([camera], [MeanIntensityPresence("other", "shelf")])
        app.service.reloader = lambda: replacement
        async with app:
            plc = await Plc(modbus_port(app)).connect()
            before = (await plc.read(Reg.MAP_ID, 1))[0]
            await plc.trigger(1)
            await wait_until(lambda: gate.entered == 1, "the inspection runs")
            await app.reload()
            now = (await plc.read(Reg.MAP_ID, 1))[0]
            assert now != before, "the new map is served while the old run goes on"
            gate.release.set()
            await plc.wait_status(Status.DONE)
            result = await plc.result()
            assert result.status == Status.DONE | Status.PASS
            assert (result.result_map_id, result.map_id) == (before, now)
            assert result.values == [], "the gate's type has no summary values"
            await plc.write_control(0)
            fresh = await plc.run(1)  # number 1 is the replacement now
            assert fresh.values == [MEAN]
            assert fresh.result_map_id == now
            plc.close()
        camera.close()

    try:
        run(body())
    finally:
        gate.release.set()


def exception_code(reply: bytes, function: int) -> int | None:
    """The exception code of a reply frame to ``function``, None when it is no exception."""
    if reply[7] == function | 0x80:
        return reply[8]
    assert reply[7] == function, reply.hex()
    return None


def test_bad_requests_are_answered_with_modbus_exceptions(tmp_path: Path) -> None:
    gate = Gate(camera="shelf")

    async def body() -> None:
        app, camera = gate_app(tmp_path, gate, unit_id=5)
        async with app:
            port = modbus_port(app)

            def read(address: int, count: int, unit: int = 5, function: int = 3) -> bytes:
                return mbap(1, unit, struct.pack(">BHH", function, address, count))

            assert exception_code(await exchange(port, read(0, SIZE)), 3) is None
            assert exception_code(await exchange(port, read(0, SIZE, function=4)), 4) is None
            for unit in (0, 255):  # "this device" on Modbus TCP
                assert exception_code(await exchange(port, read(0, 1, unit)), 3) is None
            cases = {
                "past the map": (read(SIZE - 1, 2), 3, 0x02),
                "far past the map": (read(60000, 10), 3, 0x02),
                "no register": (read(0, 0), 3, 0x03),
                "more than 125": (read(0, 126), 3, 0x03),
                "another unit": (read(0, 1, unit=9), 3, 0x0B),
                "read coils": (read(0, 1, function=1), 1, 0x01),
                "read discrete inputs": (read(0, 1, function=2), 2, 0x01),
                "write a coil": (mbap(1, 5, struct.pack(">BHH", 5, 0, 0xFF00)), 5, 0x01),
                "write STATUS": (mbap(1, 5, struct.pack(">BHH", 6, Reg.STATUS, 1)), 6, 0x02),
                "write past the map": (mbap(1, 5, struct.pack(">BHH", 6, SIZE + 3, 1)), 6, 0x02),
                "write CONTROL..STATUS": (
                    mbap(1, 5, struct.pack(">BHHBHHH", 16, 0, 3, 6, 1, 1, 1)),
                    16,
                    0x02,
                ),
                "an unknown function": (mbap(1, 5, bytes([0x63, 0, 0, 0, 1])), 0x63, 0x01),
            }
            for what, (frame, function, code) in cases.items():
                got = exception_code(await exchange(port, frame), function)
                assert got == code, f"{what}: exception {got}, expected {code}"
            # None of it touched the hand-shake: no run, no refusal, READY.
            reply = await exchange(port, read(0, 12))
            regs = struct.unpack(">12H", reply[9:])
            assert (regs[Reg.STATUS], regs[Reg.SEQUENCE], regs[Reg.REFUSALS]) == (
                Status.READY,
                0,
                0,
            )
            assert gate.entered == 0
        camera.close()

    try:
        run(body())
    finally:
        gate.release.set()


def test_modbus_map_prints_the_table_a_plc_programmer_works_from(tmp_path: Path) -> None:
    path = write_cell(tmp_path, CONFIG.replace("WORD_ORDER", "low_first"))
    out = io.StringIO()
    with contextlib.redirect_stdout(out):
        assert cli_main(["modbus-map", str(path)]) == 0
    text = out.getvalue()
    printed = printed_map(path)
    assert f"register map {printed['map_id']} (MAP_ID)" in text
    assert "word order low_first" in text
    for row in ("40001", "CONTROL", "STATUS", "ERROR_CODE", "SEQUENCE", "MAP_ID"):
        assert row in text
    assert "inspection 1 = bright (presence)" in text
    assert "inspection 7 = dark (presence)" in text
    assert "16-17" in text
    assert "40017-40018" in text
    assert "float32" in text
    assert "102" in text
    assert "acknowledge the result first" in text
    inspections = printed["inspections"]
    assert isinstance(inspections, list)
    assert [(i["number"], i["name"]) for i in inspections] == [(1, "bright"), (7, "dark")]
    assert inspections[0]["values"][0]["address"] == 16
    assert inspections[0]["values"][0]["field"] == "value"


def test_modbus_map_of_a_broken_file_names_the_error(tmp_path: Path) -> None:
    path = write_cell(tmp_path, CONFIG.replace("WORD_ORDER", "middle_first"))
    out = io.StringIO()
    with contextlib.redirect_stdout(out):
        assert cli_main(["modbus-map", str(path), "--json"]) == 2
    error = json.loads(out.getvalue())["error"]
    assert "word_order" in error["message"]
    assert "middle_first" in error["message"]


def test_pipelined_requests_are_each_answered_in_order(tmp_path: Path) -> None:
    """Modbus TCP lets a client send before its answers came: every request gets its own
    answer, in order (pymodbus's own framing answered only the last of a burst)."""
    gate = Gate(camera="shelf")

    async def body() -> None:
        app, camera = gate_app(tmp_path, gate)
        async with app:
            reader, writer = await asyncio.open_connection("127.0.0.1", modbus_port(app))
            burst = b"".join(
                mbap(tid, 1, struct.pack(">BHH", 3, Reg.STATUS, 1)) for tid in range(1, 21)
            )
            writer.write(burst[:5])  # cut anywhere: a frame may come in pieces
            await writer.drain()
            writer.write(burst[5:])
            await writer.drain()
            for tid in range(1, 21):
                reply = await reader.readexactly(11)
                assert struct.unpack(">HHHBBBH", reply) == (tid, 0, 5, 1, 3, 2, Status.READY)
            writer.close()
        camera.close()

    run(body())


def test_a_stream_that_is_not_modbus_is_closed_and_disturbs_no_one(tmp_path: Path) -> None:
    """A frame with another protocol id or an impossible length: the connection ends (Modbus
    TCP cannot find the next frame after it); a PLC on another connection works on."""
    gate = Gate(camera="shelf")
    gate.release.set()

    async def body() -> None:
        app, camera = gate_app(tmp_path, gate)
        async with app:
            port = modbus_port(app)
            plc = await Plc(port).connect()
            broken = {
                "protocol id 1": struct.pack(">HHHB", 1, 1, 6, 1) + bytes([3, 0, 0, 0, 1]),
                "length 0": struct.pack(">HHHB", 1, 0, 0, 1),
                "length 1000": struct.pack(">HHHB", 1, 0, 1000, 1) + bytes(100),
            }
            for what, data in broken.items():
                reader, writer = await asyncio.open_connection("127.0.0.1", port)
                writer.write(data + mbap(2, 1, struct.pack(">BHH", 3, 0, 1)))
                await writer.drain()
                async with asyncio.timeout(10.0):
                    assert await reader.read() == b"", f"{what}: the connection stays open"
                writer.close()
                result = await plc.run(1)
                assert result.status == Status.DONE | Status.PASS, what
            plc.close()
        camera.close()

    run(body())


def test_without_the_extra_an_enabled_modbus_is_a_configuration_error(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Not a traceback at start: check-config and serve name the key and the fix."""
    import vision_server.config.cell

    path = write_cell(tmp_path, CONFIG.replace("WORD_ORDER", "high_first"))
    monkeypatch.setattr(vision_server.config.cell, "find_spec", lambda name: None)
    with pytest.raises(ConfigError, match=r"modbus -> enabled: .*cellvision\[modbus\]"):
        load_config(path)


def test_the_server_and_its_tools_do_not_import_pymodbus_unless_modbus_is_enabled() -> None:
    """pymodbus is an optional extra: nothing else may need it."""
    code = (
        "import sys, vision_server.app, vision_server.commands.program, "
        "vision_server.commands.modbus_map; "
        "print('pymodbus' in sys.modules)"
    )
    out = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, check=True, timeout=120
    )
    assert out.stdout.strip() == "False"


SERVED = """\
server: {port: 0}
results: {enabled: true, path: results.db}
cameras:
  shelf: {source: folder, path: imgs}
inspections:
  - name: bright
    type: presence
    camera: shelf
    measure: mean_intensity
    min: 10
modbus: {enabled: true, port: 0}
"""


def test_serve_speaks_modbus_logs_its_runs_and_reloads_its_map_on_sighup(tmp_path: Path) -> None:
    """``vision-server serve`` as a process: the Modbus port it prints, the hand-shake with
    pymodbus's blocking client, each run in the result log (peer ``modbus``), and SIGHUP
    regenerating the map the PLC reads."""
    from pymodbus.client import ModbusTcpClient

    path = write_cell(tmp_path, SERVED)
    root = Path(__file__).resolve().parents[2]
    env = {k: v for k, v in os.environ.items() if not k.startswith("CELLVISION_")}
    env["PYTHONPATH"] = str(root)
    command = [sys.executable, "-m", "vision_server"]
    proc = subprocess.Popen(
        [*command, "serve", "--config", str(path)],
        cwd=root,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        env=env,
    )
    try:
        assert proc.stdout is not None
        lines = [proc.stdout.readline() for _ in range(2)]
        match = re.fullmatch(r"vision-server: Modbus TCP on 127\.0\.0\.1:(\d+)\n", lines[1])
        assert match, f"no Modbus line: {lines!r}"
        plc = ModbusTcpClient("127.0.0.1", port=int(match[1]), timeout=10.0, retries=0)
        assert plc.connect()

        def registers(address: int, count: int) -> list[int]:
            reply = plc.read_holding_registers(address, count=count, device_id=1)
            assert not reply.isError(), reply
            return list(reply.registers)

        def wait_for(bit: Status) -> None:
            for _ in range(6000):  # a PLC's scan: poll, never a verdict on time
                if bit in Status(registers(Reg.STATUS, 1)[0]):
                    return
                time.sleep(0.005)
            raise AssertionError(f"{bit!r} never came")

        for _ in range(3):
            assert not plc.write_registers(Reg.CONTROL, [1, 1], device_id=1).isError()
            wait_for(Status.DONE)
            status, error_code, sequence = registers(Reg.STATUS, 3)
            assert (status, error_code) == (Status.DONE | Status.PASS, 0)
            assert not plc.write_register(Reg.CONTROL, 0, device_id=1).isError()
            wait_for(Status.READY)
        assert sequence == 3

        path.write_text(SERVED.replace("min: 10", "min: 10\n    number: 4"), encoding="utf-8")
        new_id = printed_map(path)["map_id"]
        proc.send_signal(signal.SIGHUP)
        assert "configuration reloaded" in proc.stdout.readline()
        assert registers(Reg.MAP_ID, 1)[0] == new_id
        plc.close()
    finally:
        proc.send_signal(signal.SIGTERM)
        out, err = proc.communicate(timeout=60)
    assert proc.returncode == 0, err
    logged = subprocess.run(
        [*command, "results", "--config", str(path), "--json"],
        cwd=root,
        capture_output=True,
        text=True,
        env=env,
        timeout=120,
        check=True,
    )
    rows = [json.loads(line) for line in logged.stdout.splitlines() if line.strip()]
    rows = rows[0] if len(rows) == 1 and isinstance(rows[0], list) else rows
    assert [(r["inspection"], r["peer"], r["verdict"]) for r in rows] == [
        ("bright", "modbus", "pass")
    ] * 3


def test_a_stage_that_ignores_its_deadline_still_ends_in_done(tmp_path: Path) -> None:
    """The service answers DEADLINE_EXCEEDED at the deadline; were a stage ever to hang past
    it, the front-end ends the run itself: BUSY never stays set."""
    gate = Gate(camera="shelf")

    async def body() -> None:
        app, camera = gate_app(tmp_path, gate, deadline_s=0.2)

        async def hangs(*args: object, **kwargs: object) -> object:
            await asyncio.Event().wait()  # never set
            raise AssertionError("unreachable")

        app.service.inspect = hangs  # type: ignore[method-assign]
        async with app:
            plc = await Plc(modbus_port(app)).connect()
            result = await plc.run(1)
            assert (result.status, result.error_code) == (Status.DONE | Status.ERROR, 21)
            plc.close()
        camera.close()

    run(body())
