"""Modbus TCP framing (the MBAP header), sans-IO: bytes in, whole requests out.

pymodbus's own server framing waits forever on a frame with a bad protocol identifier, drops
a receive buffer past 1 KiB and answers only the last of several pipelined frames; the
front-end frames requests here instead and hands pymodbus whole, checked PDUs. Modbus TCP has
no way to find the next frame after a broken header, so a broken header ends the connection
(:class:`FramingError`); a whole frame whose PDU is wrong is answered with an exception.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass

MBAP_BYTES = 7
"""Transaction id (2), protocol id (2, always 0), length (2), unit id (1)."""
MAX_LENGTH = 254
"""The MBAP length field's largest value: the unit id and a PDU of at most 253 bytes."""
MIN_LENGTH = 2
"""The unit id and a function code."""

SERVED_FUNCTIONS = frozenset({3, 4, 6, 16, 22, 23})
"""Function codes answered (holding registers); every other is ILLEGAL FUNCTION."""

ILLEGAL_FUNCTION = 0x01
ILLEGAL_VALUE = 0x03
GATEWAY_NO_RESPONSE = 0x0B
"""What a request to a unit id this device is not gets, whatever its PDU (protocol/MODBUS.md
§4.3): the PDU is the other device's to judge."""
MAX_WRITE = 123
"""Registers function 16 may write at once (the Modbus limit)."""
MAX_READ_WRITE = (125, 121)
"""Registers function 23 may read and write at once (the Modbus limits)."""


class FramingError(Exception):
    """The byte stream is not Modbus TCP: no further frame can be found in it."""


@dataclass(frozen=True)
class Request:
    """One whole Modbus TCP request: ``pdu`` is the function code and its data."""

    transaction: int
    unit: int
    pdu: bytes

    @property
    def function(self) -> int:
        return self.pdu[0]


class FrameReader:
    """Cuts a connection's bytes into requests. ``feed`` returns the requests completed by
    ``data``; it holds at most one incomplete frame (at most 260 bytes)."""

    def __init__(self) -> None:
        self._buffer = bytearray()

    def feed(self, data: bytes) -> list[Request]:
        self._buffer += data
        requests = []
        while len(self._buffer) >= MBAP_BYTES:
            transaction, protocol, length, unit = struct.unpack_from(">HHHB", self._buffer)
            if protocol != 0:
                raise FramingError(f"protocol id {protocol} in an MBAP header (Modbus is 0)")
            if not MIN_LENGTH <= length <= MAX_LENGTH:
                raise FramingError(
                    f"MBAP length {length} (a request has {MIN_LENGTH}..{MAX_LENGTH})"
                )
            end = MBAP_BYTES - 1 + length
            if len(self._buffer) < end:
                break
            requests.append(Request(transaction, unit, bytes(self._buffer[MBAP_BYTES:end])))
            del self._buffer[:end]
        return requests


def pdu_problem(pdu: bytes) -> int | None:
    """The exception code a PDU earns by its function, its length and its register counts
    alone (None: fine), before any address is looked at. pymodbus decodes a PDU that is too
    long without a word; the protocol's lengths are exact."""
    function = pdu[0]
    if function not in SERVED_FUNCTIONS:
        return ILLEGAL_FUNCTION
    fixed = {3: 5, 4: 5, 6: 5, 22: 7}
    if function in fixed:
        return None if len(pdu) == fixed[function] else ILLEGAL_VALUE
    header = 6 if function == 16 else 10  # up to and including the byte count
    if len(pdu) < header or len(pdu) != header + pdu[header - 1]:
        return ILLEGAL_VALUE
    if function == 16:
        (count,) = struct.unpack_from(">H", pdu, 3)
        if not 1 <= count <= MAX_WRITE or pdu[5] != 2 * count:
            return ILLEGAL_VALUE
        return None
    _, read_count, _, write_count, byte_count = struct.unpack_from(">HHHHB", pdu, 1)
    most_read, most_written = MAX_READ_WRITE
    if not 1 <= read_count <= most_read or not 1 <= write_count <= most_written:
        return ILLEGAL_VALUE
    return None if byte_count == 2 * write_count else ILLEGAL_VALUE


@dataclass(frozen=True)
class ReadWrite:
    """A function 23 request (read/write multiple registers): the write, then the read, both
    checked before either is done (``ModbusFrontend.read_write``)."""

    read_address: int
    read_count: int
    write_address: int
    values: tuple[int, ...]


def read_write(pdu: bytes) -> ReadWrite:
    """The fields of a function 23 PDU that :func:`pdu_problem` passed."""
    read_address, read_count, write_address, write_count = struct.unpack_from(">HHHH", pdu, 1)
    values = struct.unpack_from(f">{write_count}H", pdu, 10)
    return ReadWrite(read_address, read_count, write_address, values)


def frame(transaction: int, unit: int, pdu: bytes) -> bytes:
    """A reply frame carrying ``pdu``."""
    return struct.pack(">HHHB", transaction, 0, len(pdu) + 1, unit) + pdu


def exception_frame(request: Request, code: int) -> bytes:
    """The exception reply to ``request``: its function code with the high bit, and ``code``."""
    return frame(request.transaction, request.unit, bytes([(request.function | 0x80) & 0xFF, code]))


__all__ = [
    "GATEWAY_NO_RESPONSE",
    "ILLEGAL_FUNCTION",
    "ILLEGAL_VALUE",
    "MAX_LENGTH",
    "MAX_READ_WRITE",
    "MAX_WRITE",
    "MBAP_BYTES",
    "SERVED_FUNCTIONS",
    "FrameReader",
    "FramingError",
    "ReadWrite",
    "Request",
    "exception_frame",
    "frame",
    "pdu_problem",
    "read_write",
]
