"""Hostile Modbus frames against the Modbus front-end while a good PLC keeps doing the
hand-shake, then the binary protocol's conformance suite against the same server (issue 20,
"Measured").

The short form (2,000 hostile frames) runs in ``make test``; the long form::

    MODBUS_FUZZ_FRAMES=20000 python -m pytest tests/vision_server/test_modbus_fuzz.py -q

Eight connections send bursts without waiting for answers. A clean burst holds only whole,
well-formed frames that must each be refused or answered exactly (bad unit ids, illegal
functions, addresses past the map, register counts out of range, writes to registers a PLC may
only read, plain reads): every answer is checked against the one the test predicts, in order,
and the burst's closing probe is answered. A dirty burst holds random bytes, MBAP lengths that
do not match their PDU and frames cut off by a closed connection: every answer that comes must
be a well-formed Modbus TCP frame, and the server may end the connection (Modbus TCP cannot
find the next frame after a broken one). Meanwhile one PLC runs inspection 2 (a server
camera's) again and again and checks each result. Afterwards a fresh PLC is served and
``python -m protocol.conformance`` (its ``main``) passes against the same server.
"""

from __future__ import annotations

import asyncio
import os
import random
import struct
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
from loopback import run
from plc import Plc, Result

from protocol.conformance.__main__ import main as conformance_main
from vision_server import Catalog
from vision_server.app import App
from vision_server.cameras import FolderCamera, FolderCameraSettings
from vision_server.config import ModbusSettings, ServerSettings
from vision_server.frontends.modbus_map import SIZE, Reg, Status
from vision_server.service.builtin import MeanIntensityPresence, builtin_catalog

FRAMES = int(os.environ.get("MODBUS_FUZZ_FRAMES", "2000"))
CONNECTIONS = 8
SERVED_UNITS = (0, 1, 255)
PROBE_TID = 0xFFFF
MEAN = 100.0


@dataclass(frozen=True)
class Frame:
    """One frame to send; ``expect``: the answer's function byte and its first data byte
    (the exception code, or a read's byte count), None for no prediction (dirty frames)."""

    data: bytes
    expect: tuple[int | None, int] | None
    """None for a plain read's function (3 or 4, as asked)."""


def mbap(tid: int, unit: int, pdu: bytes) -> bytes:
    return struct.pack(">HHHB", tid, 0, len(pdu) + 1, unit) + pdu


def clean_frame(rng: random.Random, tid: int) -> Frame:
    """A whole, well-formed frame and the answer it must get."""
    unit = rng.choice(SERVED_UNITS)
    kind = rng.randrange(6)
    if kind == 0:  # a unit this device is not
        bad = rng.choice([u for u in range(2, 255)])
        count = rng.randrange(1, 10)
        return Frame(mbap(tid, bad, struct.pack(">BHH", 3, 0, count)), (0x83, 0x0B))
    if kind == 1:  # functions not served: coils, diagnostics, identification, unknown
        function = rng.choice([1, 2, 5, 15, 7, 8, 11, 17, 20, 43, 0x41, 0x63, 0x7F])
        data = rng.randbytes(rng.randrange(0, 8))
        return Frame(mbap(tid, unit, bytes([function]) + data), ((function | 0x80) & 0xFF, 0x01))
    if kind == 2:  # past the map
        function = rng.choice([3, 4])
        address = rng.randrange(SIZE - 5, 65536)
        count = rng.randrange(max(1, SIZE - address + 1), 126) if address < SIZE else 1
        return Frame(
            mbap(tid, unit, struct.pack(">BHH", function, address, count)), (function | 0x80, 0x02)
        )
    if kind == 3:  # a register count out of range
        count = rng.choice([0, 126, 200, 0xFFFF])
        return Frame(mbap(tid, unit, struct.pack(">BHH", 3, 0, count)), (0x83, 0x03))
    if kind == 4:  # writes to what a PLC may only read (never to CONTROL or INSPECTION)
        address = rng.randrange(Reg.STATUS, SIZE + 10)
        if rng.random() < 0.5:
            pdu = struct.pack(">BHH", 6, address, rng.randrange(65536))
            return Frame(mbap(tid, unit, pdu), (0x86, 0x02))
        values = [rng.randrange(65536) for _ in range(rng.randrange(1, 5))]
        pdu = struct.pack(
            f">BHHB{len(values)}H", 16, address, len(values), 2 * len(values), *values
        )
        return Frame(mbap(tid, unit, pdu), (0x90, 0x02))
    count = rng.randrange(1, SIZE + 1)  # a plain read, answered with its registers
    pdu = struct.pack(">BHH", rng.choice([3, 4]), 0, count)
    return Frame(mbap(tid, unit, pdu), (None, 2 * count))


def dirty_frame(rng: random.Random, tid: int) -> Frame:
    kind = rng.randrange(3)
    if kind == 0:  # random bytes
        return Frame(rng.randbytes(rng.randrange(1, 300)), None)
    if kind == 1:  # an MBAP length that does not match its PDU
        pdu = struct.pack(">BHH", 3, 0, 1) + rng.randbytes(rng.randrange(0, 4))
        length = rng.choice([0, 1, 2, len(pdu), len(pdu) + 5, 254, 255, 0xFFFF])
        return Frame(struct.pack(">HHHB", tid, 0, length, 1) + pdu, None)
    # a header with another protocol id
    return Frame(
        struct.pack(">HHHB", tid, rng.randrange(1, 65536), 6, 1) + bytes([3, 0, 0, 0, 1]), None
    )


def bursts(rng: random.Random, count: int) -> list[tuple[bool, list[Frame]]]:
    """``count`` frames in bursts: (clean?, frames)."""
    out: list[tuple[bool, list[Frame]]] = []
    made = 0
    while made < count:
        size = min(rng.randrange(5, 60), count - made)
        clean = rng.random() < 0.6
        make = clean_frame if clean else dirty_frame
        out.append((clean, [make(rng, 1 + i) for i in range(size)]))
        made += size
    return out


async def read_frame(reader: asyncio.StreamReader) -> bytes | None:
    """One whole answer frame; None at the end of the connection."""
    try:
        header = await reader.readexactly(7)
        (protocol, length) = struct.unpack(">HH", header[2:6])
        assert protocol == 0, f"an answer with protocol id {protocol}"
        assert 2 <= length <= 254, f"an answer with MBAP length {length}"
        return header + await reader.readexactly(length - 1)
    except asyncio.IncompleteReadError as exc:
        partial = exc.partial
    assert partial == b"", f"an answer cut in the middle: {partial.hex()}"
    return None


def check_answer(answer: bytes, frame: Frame, tid: int, bad: list[str]) -> None:
    got_tid, _, _, _, function = struct.unpack(">HHHBB", answer[:8])
    if got_tid != tid:
        bad.append(f"answer tid {got_tid}, expected {tid}")
        return
    assert frame.expect is not None
    want_function, want_byte = frame.expect
    if want_function is None:  # a plain read: its byte count
        if function not in (3, 4) or answer[8] != want_byte:
            bad.append(f"a read answered {answer.hex()}")
        return
    if (function, answer[8]) != (want_function, want_byte):
        want = f"{want_function:#x} {want_byte:#x}"
        bad.append(f"{frame.data.hex()} answered {answer.hex()}, expected {want}")


async def attacker(
    port: int, plan: list[tuple[bool, list[Frame]]], rng: random.Random, bad: list[str]
) -> int:
    """Send each burst on a connection of its own (a dirty one may be closed by the server);
    returns how many frames were answered."""
    answered = 0
    probe = mbap(PROBE_TID, 1, struct.pack(">BHH", 3, Reg.STATUS, 1))
    for clean, frames in plan:
        reader, writer = await asyncio.open_connection("127.0.0.1", port)
        writer.write(b"".join(f.data for f in frames) + (probe if clean else b""))
        if not clean and rng.random() < 0.5:  # a frame cut off by the end of the connection
            writer.write(probe[: rng.randrange(1, len(probe))])
        await writer.drain()
        writer.write_eof()
        if clean:
            for i, frame in enumerate(frames):
                answer = await read_frame(reader)
                if answer is None:
                    bad.append(f"a clean burst's frame {i} got no answer")
                    break
                check_answer(answer, frame, 1 + i, bad)
                answered += 1
            last = await read_frame(reader)
            if last is None or struct.unpack(">H", last[:2])[0] != PROBE_TID:
                bad.append(f"a clean burst's probe got {last!r}")
        else:
            while (answer := await read_frame(reader)) is not None:
                answered += 1
        writer.close()
    return answered


async def good_plc(port: int, done: asyncio.Event) -> tuple[int, list[str]]:
    """Run inspection 2 until ``done`` (at least 5 times); returns the runs and failures."""
    plc = await Plc(port).connect()
    failures: list[str] = []
    runs = 0
    sequence = (await plc.read(Reg.SEQUENCE, 1))[0]
    while not done.is_set() or runs < 5:
        result = await plc.run(2)
        runs += 1
        sequence += 1
        got = (result.status, result.error_code, result.inspection, result.sequence, result.values)
        want = (Status.DONE | Status.PASS, 0, 2, sequence & 0xFFFF, [MEAN])
        if got != want or result.refusals != 0:
            failures.append(f"run {runs}: {got}, refusals {result.refusals}")
    plc.close()
    return runs, failures


def test_hostile_frames_disturb_neither_a_good_plc_nor_the_binary_protocol(tmp_path: Path) -> None:
    (tmp_path / "imgs").mkdir()
    cv2.imwrite(str(tmp_path / "imgs" / "a.png"), np.full((48, 64), int(MEAN), np.uint8))
    camera = FolderCamera("shelf", FolderCameraSettings(tmp_path / "imgs"))
    camera.open()
    builtin = builtin_catalog()
    catalog = Catalog.build(
        [*builtin.cameras.values(), camera],
        [*builtin.inspections.values(), MeanIntensityPresence("part", "shelf", 10.0, 255.0)],
    )
    modbus = ModbusSettings(enabled=True, port=0, max_connections=16)
    app = App(catalog, ServerSettings(port=0, workers=2), modbus=modbus)
    rng = random.Random(20)
    plans = [bursts(rng, FRAMES // CONNECTIONS) for _ in range(CONNECTIONS)]
    clean_frames = sum(len(f) for plan in plans for clean, f in plan if clean)

    async def body() -> tuple[int, list[str], list[str], list[int], Result, int]:
        async with app:
            assert app.modbus is not None
            port = app.modbus.port
            done = asyncio.Event()
            good = asyncio.create_task(good_plc(port, done))
            bad: list[str] = []
            answered = await asyncio.gather(
                *(attacker(port, plan, random.Random(i), bad) for i, plan in enumerate(plans))
            )
            done.set()
            runs, failures = await good
            # Afterwards: a fresh PLC, and the binary protocol's conformance suite.
            after = await Plc(port).connect()
            fresh = await after.run(2)
            after.close()
            conformance = await asyncio.to_thread(conformance_main, [f"127.0.0.1:{app.port}"])
            return runs, failures, bad, answered, fresh, conformance

    try:
        runs, failures, bad, answered, fresh, conformance = run(
            body(), timeout_s=60.0 + FRAMES / 50
        )
    finally:
        camera.close()
    assert bad == []
    assert failures == []
    assert runs >= 5
    assert sum(answered) >= clean_frames, "every clean frame is answered"
    assert fresh.values == [MEAN]
    assert conformance == 0, "the conformance suite failed (its report is above)"
