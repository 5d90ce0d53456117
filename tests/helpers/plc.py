"""A PLC for the Modbus tests: pymodbus's own client doing the hand-shake of protocol/MODBUS.md
as a PLC program would (poll STATUS until DONE, read the result, acknowledge), and raw frames
for what no well-behaved client sends.

Importable as ``plc`` (pytest's ``pythonpath`` includes tests/helpers).
"""

from __future__ import annotations

import asyncio
import struct
from dataclasses import dataclass

from pymodbus.client import AsyncModbusTcpClient

from vision_server.frontends.modbus_map import VALUES, Control, Reg, Status, decode_float

UNIT = 1


@dataclass(frozen=True)
class Result:
    """What a PLC reads once DONE is set."""

    status: Status
    error_code: int
    sequence: int
    inspection: int
    values: list[float]
    map_id: int
    result_map_id: int
    refusal: int
    refusals: int


class Plc:
    """One PLC connection. ``word_order`` is what its program was written for."""

    def __init__(self, port: int, word_order: str = "high_first") -> None:
        self.client = AsyncModbusTcpClient(
            "127.0.0.1", port=port, timeout=10.0, retries=0, reconnect_delay=0
        )
        self.word_order = word_order
        self.control = 0

    async def connect(self) -> Plc:
        assert await self.client.connect(), "the PLC cannot connect"
        return self

    def close(self) -> None:
        self.client.close()

    async def read(self, address: int, count: int) -> list[int]:
        reply = await self.client.read_holding_registers(address, count=count, device_id=UNIT)
        assert not reply.isError(), f"read {address}+{count}: {reply}"
        return list(reply.registers)

    async def status(self) -> Status:
        return Status((await self.read(Reg.STATUS, 1))[0])

    async def write_control(self, value: int) -> None:
        reply = await self.client.write_register(Reg.CONTROL, value, device_id=UNIT)
        assert not reply.isError(), f"write CONTROL={value}: {reply}"
        self.control = value

    async def trigger(self, number: int) -> None:
        """Select and raise TRIGGER in one write (INSPECTION is applied first)."""
        value = self.control | Control.TRIGGER
        reply = await self.client.write_registers(Reg.CONTROL, [value, number], device_id=UNIT)
        assert not reply.isError(), f"trigger {number}: {reply}"
        self.control = value

    async def wait_status(self, wanted: Status, timeout_s: float = 30.0) -> Status:
        """Poll STATUS until every bit of ``wanted`` is set (as a PLC's scan does)."""
        async with asyncio.timeout(timeout_s):
            while True:
                status = await self.status()
                if wanted in status:
                    return status
                await asyncio.sleep(0.005)

    async def result(self) -> Result:
        regs = await self.read(0, VALUES + 2 * 29)
        count = regs[Reg.VALUE_COUNT]
        values = [
            decode_float((regs[VALUES + 2 * i], regs[VALUES + 2 * i + 1]), self.word_order)
            for i in range(count)
        ]
        return Result(
            Status(regs[Reg.STATUS]),
            regs[Reg.ERROR_CODE],
            regs[Reg.SEQUENCE],
            regs[Reg.RESULT_INSPECTION],
            values,
            regs[Reg.MAP_ID],
            regs[Reg.RESULT_MAP_ID],
            regs[Reg.REFUSAL],
            regs[Reg.REFUSALS],
        )

    async def run(self, number: int) -> Result:
        """The whole hand-shake: trigger, wait for DONE, read, acknowledge (clear TRIGGER),
        wait for READY."""
        await self.trigger(number)
        await self.wait_status(Status.DONE)
        result = await self.result()
        await self.write_control(self.control & ~Control.TRIGGER)
        await self.wait_status(Status.READY)
        return result


def mbap(transaction: int, unit: int, pdu: bytes, *, length: int | None = None) -> bytes:
    """A Modbus TCP frame: MBAP header (protocol 0) and the PDU."""
    size = len(pdu) + 1 if length is None else length
    return struct.pack(">HHHB", transaction, 0, size, unit) + pdu


async def exchange(port: int, frame: bytes, timeout_s: float = 10.0) -> bytes:
    """Send one frame on a fresh connection; the whole reply frame."""
    reader, writer = await asyncio.open_connection("127.0.0.1", port)
    try:
        writer.write(frame)
        await writer.drain()
        async with asyncio.timeout(timeout_s):
            header = await reader.readexactly(7)
            (size,) = struct.unpack(">H", header[4:6])
            return header + await reader.readexactly(size - 1)
    finally:
        writer.close()


__all__ = ["UNIT", "Plc", "Result", "exchange", "mbap"]
