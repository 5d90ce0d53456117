"""The Modbus hand-shake as a state machine over the register bank (protocol/MODBUS.md §3):
no I/O, no pymodbus, no asyncio. The adapter (:mod:`.modbus`) feeds it the PLC's reads and
writes and the inspections' outcomes; it says which inspection to start.

Edges of the bits the PLC writes drive it, never levels: a PLC that writes its whole control
word every scan (as most do) repeats a level, and a repeated level must change nothing.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

from .modbus_map import (
    SIZE,
    VALUES,
    WRITABLE,
    Control,
    Refusal,
    Reg,
    RegisterMap,
    Status,
)

MAX_READ = 125
"""Registers one read may ask for (the Modbus limit of function 3 and 4)."""


class IllegalAddress(Exception):
    """A read or write outside the map, or a write to a register the PLC may only read."""


class IllegalValue(Exception):
    """A read of no register or of more than the protocol allows at once."""


@dataclass(frozen=True)
class Outcome:
    """How a run ended: ``error_code`` 0 when the inspection answered (then ``passed`` is its
    verdict), else the :class:`protocol.ErrorCode` number; ``values`` in the order of the map
    the run started with, whose checksum is ``map_id``."""

    number: int
    passed: bool
    error_code: int
    values: tuple[float, ...]
    map_id: int


class Handshake:
    """The register bank of one Modbus device and the rules that change it. See the module."""

    def __init__(self, register_map: RegisterMap) -> None:
        self.registers = [0] * SIZE
        self.map = register_map
        self.accepting = True
        """False once the server stops: READY stays clear and every trigger edge is refused
        with NOT_READY (before any other refusal: nothing will run again)."""
        self._written = 0
        """CONTROL as the PLC last wrote it (edges are against this)."""
        self.set_map(register_map)
        self.registers[Reg.STATUS] = Status.READY

    # ------------------------------------------------------------------ the map

    def set_map(self, register_map: RegisterMap) -> None:
        """Serve ``register_map`` from now on (a reload). The current result keeps the layout
        it was written in; RESULT_MAP_ID says which."""
        self.map = register_map
        self.registers[Reg.MAP_ID] = register_map.map_id
        self.registers[Reg.WORD_ORDER] = 0 if register_map.word_order == "high_first" else 1

    @property
    def status(self) -> Status:
        return Status(self.registers[Reg.STATUS])

    # ------------------------------------------------------------------ the PLC's requests

    def check_read(self, address: int, count: int) -> None:
        """Raise what a read of ``count`` registers from ``address`` would; change nothing."""
        if not 1 <= count <= MAX_READ:
            raise IllegalValue(f"a read of {count} registers (1..{MAX_READ})")
        if address < 0 or address + count > SIZE:
            raise IllegalAddress(f"registers {address}..{address + count - 1} (0..{SIZE - 1})")

    def read(self, address: int, count: int) -> list[int]:
        self.check_read(address, count)
        return self.registers[address : address + count]

    def check_write(self, address: int, values: Sequence[int]) -> None:
        """Raise what a write of ``values`` from ``address`` would; change nothing. A request
        that reads and writes (function 23) checks both before either is done, so that a
        refused request writes nothing and triggers nothing."""
        touched = range(address, address + len(values))
        if not values or any(a not in WRITABLE for a in touched):
            raise IllegalAddress(
                f"registers {address}..{address + len(values) - 1}: only "
                f"{Reg.CONTROL} (CONTROL) and {Reg.INSPECTION} (INSPECTION) are writable"
            )
        if any(not 0 <= v <= 0xFFFF for v in values):
            raise IllegalValue("a register holds 0..65535")

    def write(self, address: int, values: Sequence[int]) -> int | None:
        """Apply a write of registers ``address`` onwards; the inspection number to start
        when it makes a trigger edge that is accepted, else None. A write that touches a
        register the PLC may not write changes nothing (IllegalAddress). INSPECTION is
        applied before CONTROL, so one write of both selects and triggers."""
        self.check_write(address, values)
        touched = range(address, address + len(values))
        written = dict(zip(touched, values, strict=True))
        if Reg.INSPECTION in written:
            self.registers[Reg.INSPECTION] = written[Reg.INSPECTION] & 0xFFFF
        if Reg.CONTROL in written:
            return self._control(written[Reg.CONTROL] & 0xFFFF)
        return None

    def _control(self, value: int) -> int | None:
        rose = value & ~self._written
        fell = self._written & ~value
        self._written = value
        self.registers[Reg.CONTROL] = value
        status = self.status
        if Status.DONE in status and (fell & Control.TRIGGER or rose & Control.ACK):
            # Acknowledged: the result stays readable (PASS, ERROR, codes, values) until the
            # next accepted trigger; only DONE goes.
            status &= ~Status.DONE
            if self.accepting:
                status |= Status.READY
            self.registers[Reg.STATUS] = status
        if not rose & Control.TRIGGER:
            return None
        if not self.accepting:  # first: whatever else there is, nothing will run again
            self._refuse(Refusal.NOT_READY)
        elif Status.BUSY in status:
            self._refuse(Refusal.TRIGGER_WHILE_BUSY)
        elif Status.DONE in status:
            self._refuse(Refusal.NOT_ACKNOWLEDGED)
        else:
            return self._accept()
        return None

    def _refuse(self, why: Refusal) -> None:
        """A refused edge leaves the run or result there is alone."""
        self.registers[Reg.REFUSAL] = why
        self.registers[Reg.REFUSALS] = (self.registers[Reg.REFUSALS] + 1) & 0xFFFF

    def _accept(self) -> int:
        regs = self.registers
        regs[Reg.STATUS] = Status.BUSY
        regs[Reg.REFUSAL] = Refusal.NONE
        regs[Reg.ERROR_CODE] = 0
        regs[Reg.RESULT_INSPECTION] = 0
        regs[Reg.VALUE_COUNT] = 0
        regs[Reg.RESULT_MAP_ID] = 0
        regs[VALUES:] = [0] * (SIZE - VALUES)
        return regs[Reg.INSPECTION]

    # ------------------------------------------------------------------ the server's side

    def finish(self, outcome: Outcome) -> None:
        """Publish a run's result and set DONE, all at once (a PLC never reads DONE with the
        values half written: reads and this run on one thread)."""
        regs = self.registers
        words: list[int] = []
        for value in outcome.values:
            words.extend(self.map.words(value))
        regs[VALUES:] = words + [0] * (SIZE - VALUES - len(words))
        regs[Reg.VALUE_COUNT] = len(outcome.values)
        regs[Reg.RESULT_INSPECTION] = outcome.number & 0xFFFF
        regs[Reg.ERROR_CODE] = outcome.error_code
        regs[Reg.RESULT_MAP_ID] = outcome.map_id
        regs[Reg.SEQUENCE] = (regs[Reg.SEQUENCE] + 1) & 0xFFFF
        status = Status.DONE
        if outcome.error_code:
            status |= Status.ERROR
        elif outcome.passed:
            status |= Status.PASS
        regs[Reg.STATUS] = status

    def stop_accepting(self) -> None:
        """The server stops: no READY from now on, every trigger edge refused with NOT_READY
        (a run still going finishes, or is ended by the adapter with SHUTTING_DOWN)."""
        self.accepting = False
        self.registers[Reg.STATUS] &= ~Status.READY


__all__ = ["MAX_READ", "Handshake", "IllegalAddress", "IllegalValue", "Outcome"]
