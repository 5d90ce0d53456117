"""The Modbus register map (protocol/MODBUS.md): fixed hand-shake registers, then the current
result's values as 32-bit IEEE floats, laid out per inspection from the configuration's
``number:`` and ``output:`` keys.

Pure data, no I/O and no pymodbus: ``vision-server modbus-map`` prints the same map the server
serves, without the optional extra installed. Addresses are the protocol's 0-based register
addresses; a PLC tool's "4xxxx" reference is 40001 + address.
"""

from __future__ import annotations

import math
import struct
import zlib
from collections.abc import Iterable, Mapping
from dataclasses import dataclass
from enum import IntEnum, IntFlag
from typing import Any

from protocol import ErrorCode

from ..config import MODBUS_WORD_ORDERS as WORD_ORDERS
from ..inspections import MAX_FIELDS, POSE, RESULT_KINDS, OutputField, numbers_by_position
from ..service import Catalog
from .line import Answerable, answerable
from .line_poses import CONVENTIONS


class Reg(IntEnum):
    """The fixed registers (holding registers, 0-based addresses)."""

    CONTROL = 0
    INSPECTION = 1
    STATUS = 2
    ERROR_CODE = 3
    SEQUENCE = 4
    RESULT_INSPECTION = 5
    VALUE_COUNT = 6
    REFUSAL = 7
    REFUSALS = 8
    MAP_ID = 9
    RESULT_MAP_ID = 10
    WORD_ORDER = 11


WRITABLE = frozenset({Reg.CONTROL, Reg.INSPECTION})
"""The registers a PLC writes; writing any other is answered ILLEGAL DATA ADDRESS."""
VALUES = 16
POSE_FORMAT = "text"
"""The convention of a base-frame pose on Modbus: mm, and W P R in degrees (protocol/LINE.md
§5.7). A tool camera's pose needs the robot's TCP pose, which Modbus does not carry: its
values are the output's ``missing``."""
"""The first register of the result's values: value k at VALUES + 2k and VALUES + 2k + 1."""
FLOAT32_MAX = 3.4028234663852886e38
"""The largest finite IEEE-754 single."""
SIZE = VALUES + 2 * MAX_FIELDS
"""Registers served (0 .. SIZE - 1); a read or write past them is ILLEGAL DATA ADDRESS."""


class Control(IntFlag):
    """Bits of CONTROL, written by the PLC."""

    TRIGGER = 1 << 0
    ACK = 1 << 1


class Status(IntFlag):
    """Bits of STATUS, set by the server."""

    READY = 1 << 0
    BUSY = 1 << 1
    DONE = 1 << 2
    PASS = 1 << 3
    ERROR = 1 << 4


class Refusal(IntEnum):
    """Why a trigger was refused (REFUSAL). Outside the range of :class:`protocol.ErrorCode`,
    whose numbers ERROR_CODE carries, so that one table of codes serves both registers."""

    NONE = 0
    TRIGGER_WHILE_BUSY = 101
    NOT_ACKNOWLEDGED = 102
    NOT_READY = 103


@dataclass(frozen=True)
class MappedInspection:
    """One inspection as the map serves it: its number, and its output's values in order."""

    number: int
    target: Answerable

    @property
    def fields(self) -> tuple[OutputField, ...]:
        return self.target.output.fields

    @property
    def values(self) -> tuple[MappedValue, ...]:
        """The values in register order: a base-frame ``pose`` field is six of them (x, y, z
        in mm; w, p, r in degrees, fixed axes: the ``text`` convention, protocol/LINE.md
        §5.7)."""
        out: list[MappedValue] = []
        for f in self.fields:
            if f.name == POSE:
                out += [MappedValue(f"pose.{a}", f, "mm") for a in "xyz"]
                rotation = CONVENTIONS[POSE_FORMAT].rotation
                out += [MappedValue(f"pose.{a}", f, "deg") for a in rotation]
            else:
                out.append(MappedValue(f.name, f, field_units(self.target.type, f)))
        return tuple(out)


@dataclass(frozen=True)
class MappedValue:
    """One float32 of a result: its name, the output field it comes from, its units."""

    name: str
    field: OutputField
    units: str


@dataclass(frozen=True)
class RegisterMap:
    """The map of one configuration: the inspections by number, and the word order."""

    inspections: Mapping[int, MappedInspection]
    word_order: str = "high_first"

    @property
    def map_id(self) -> int:
        """A 16-bit checksum of everything a PLC program depends on (numbers, fields, scales,
        word order): served in MAP_ID and printed with the table, so a PLC can tell that the
        map it was written against is still the one served."""
        parts = [self.word_order]
        for number, mapped in sorted(self.inspections.items()):
            fields = ",".join(
                f"{v.name}*{v.field.scale!r}/{v.field.decimals}" for v in mapped.values
            )
            parts.append(f"{number}={mapped.target.name}:{mapped.target.type}:{fields}")
        return zlib.crc32("\n".join(parts).encode("utf-8")) & 0xFFFF

    def words(self, value: float) -> tuple[int, int]:
        """``value`` as an IEEE-754 float32 in two registers, in this map's word order. A
        value beyond float32's range is sent as an infinity of its sign (packing it would
        fail, and a result must always be published)."""
        if math.isfinite(value) and abs(value) > FLOAT32_MAX:
            value = math.copysign(math.inf, value)
        high, low = struct.unpack(">HH", struct.pack(">f", value))
        return (high, low) if self.word_order == "high_first" else (low, high)


def build_map(numbered: Iterable[tuple[int, Answerable]], word_order: str) -> RegisterMap:
    """The map of inspections given as ``(number, answerable)``."""
    if word_order not in WORD_ORDERS:
        raise ValueError(f"word_order must be one of {', '.join(WORD_ORDERS)}, got {word_order!r}")
    return RegisterMap({n: MappedInspection(n, a) for n, a in numbered}, word_order)


def config_map(
    inspections: Iterable[Any], word_order: str, catalog: Catalog | None = None
) -> RegisterMap:
    """The map of a configuration's inspections (specs or built inspections: anything with a
    name, a type and optionally ``number`` and ``output``), in configuration order.
    ``catalog``: the served one, where a base-frame output finds its camera's intrinsics (the
    map's layout does not need them)."""
    listed = list(inspections)
    numbers = numbers_by_position((i.name, getattr(i, "number", None)) for i in listed)
    by_name = {i.name: i for i in listed}
    return build_map(
        ((n, answerable(by_name[name], catalog)) for n, name in numbers.items()), word_order
    )


def decode_float(words: tuple[int, int], word_order: str) -> float:
    """The float32 in two registers read in ``word_order`` (what a PLC does; for tests)."""
    high, low = words if word_order == "high_first" else (words[1], words[0])
    value: float = struct.unpack(">f", struct.pack(">HH", high, low))[0]
    return value


# ----------------------------------------------------------------------------- the table


@dataclass(frozen=True)
class Row:
    """One line of the table a PLC programmer works from."""

    address: int
    type: str
    access: str
    name: str
    meaning: str
    units: str = ""

    @property
    def reference(self) -> int:
        """The "4xxxx" holding-register reference of PLC tools (1-based)."""
        return 40001 + self.address

    @property
    def width(self) -> int:
        """Registers the value takes."""
        return 2 if self.type == "float32" else 1


FIXED_ROWS = (
    Row(Reg.CONTROL, "bits", "R/W", "CONTROL", "bit 0 TRIGGER (rising edge runs), bit 1 ACK"),
    Row(Reg.INSPECTION, "u16", "R/W", "INSPECTION", "number of the inspection the trigger runs"),
    Row(
        Reg.STATUS,
        "bits",
        "R",
        "STATUS",
        "bit 0 READY, 1 BUSY, 2 DONE, 3 PASS, 4 ERROR",
    ),
    Row(Reg.ERROR_CODE, "u16", "R", "ERROR_CODE", "0, or why the result is an error"),
    Row(Reg.SEQUENCE, "u16", "R", "SEQUENCE", "results so far (mod 65536), +1 at each DONE"),
    Row(
        Reg.RESULT_INSPECTION,
        "u16",
        "R",
        "RESULT_INSPECTION",
        "number of the inspection the result is of",
    ),
    Row(Reg.VALUE_COUNT, "u16", "R", "VALUE_COUNT", "values the result has"),
    Row(Reg.REFUSAL, "u16", "R", "REFUSAL", "0, or why the last trigger edge was refused"),
    Row(Reg.REFUSALS, "u16", "R", "REFUSALS", "refused trigger edges so far (mod 65536)"),
    Row(Reg.MAP_ID, "u16", "R", "MAP_ID", "checksum of the map now served"),
    Row(Reg.RESULT_MAP_ID, "u16", "R", "RESULT_MAP_ID", "checksum of the map the result is in"),
    Row(Reg.WORD_ORDER, "u16", "R", "WORD_ORDER", "0 high word first, 1 low word first"),
)


ERROR_MEANINGS: dict[int, str] = {
    ErrorCode.UNKNOWN_INSPECTION: "no inspection has the number in INSPECTION",
    ErrorCode.BAD_IMAGE: "the inspection takes images in the request: not for Modbus",
    ErrorCode.IMAGE_TOO_LARGE: "the camera's image has more pixels than the server allows",
    ErrorCode.CAMERA_UNAVAILABLE: "the inspection's camera gave no frame",
    ErrorCode.INSPECTION_FAILED: "the inspection could not be computed on this image",
    ErrorCode.INVALID_ARGUMENT: "the inspection refused its settings",
    ErrorCode.BUSY: "the server is over capacity: trigger again later",
    ErrorCode.DEADLINE_EXCEEDED: "no result within deadline_s of the trigger edge",
    ErrorCode.SHUTTING_DOWN: "the server stopped before the result",
    ErrorCode.INTERNAL_ERROR: "a bug in the server (logged); the next trigger works",
}
"""What ERROR_CODE may hold (the binary protocol's numbers, protocol/SPEC.md)."""
REFUSAL_MEANINGS: dict[int, str] = {
    Refusal.TRIGGER_WHILE_BUSY: "a trigger edge while BUSY: the run in progress goes on",
    Refusal.NOT_ACKNOWLEDGED: "a trigger edge while DONE: acknowledge the result first",
    Refusal.NOT_READY: "a trigger edge while the server stops",
}
"""What REFUSAL may hold."""


def field_units(inspection_type: str, output_field: OutputField) -> str:
    """The unit of a value as sent: its summary value's, with the output's scale."""
    kind = RESULT_KINDS.get(inspection_type)
    unit = "" if kind is None else kind.units.get(output_field.name, "")
    if output_field.scale == 1.0:
        return unit
    if unit == "m" and output_field.scale == 1000.0:
        return "mm"
    return f"{unit} x {output_field.scale:g}".strip()


def value_rows(mapped: MappedInspection) -> list[Row]:
    """The value registers of one inspection's result."""
    return [
        Row(VALUES + 2 * index, "float32", "R", f"VALUE_{index + 1}", value.name, value.units)
        for index, value in enumerate(mapped.values)
    ]


__all__ = [
    "ERROR_MEANINGS",
    "FIXED_ROWS",
    "REFUSAL_MEANINGS",
    "SIZE",
    "VALUES",
    "WORD_ORDERS",
    "WRITABLE",
    "Control",
    "MappedInspection",
    "MappedValue",
    "POSE_FORMAT",
    "Reg",
    "Refusal",
    "RegisterMap",
    "Row",
    "Status",
    "build_map",
    "config_map",
    "decode_float",
    "field_units",
    "value_rows",
]
