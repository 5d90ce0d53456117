"""Test clients that read the line protocol's answers exactly as robot controllers do:
URScript's socket_read_ascii_float, RAPID's SocketReceive and StrToVal, EthernetKRL's stream
element and KRL's SREAD, KAREL's READ (str::n), SUB_STR and CNV_STR_REAL (protocol/LINE.md §5).

:func:`socket_read_ascii_float` and :func:`read_line` (URScript's rules) are
:mod:`robot_client.controllers.urscript`'s, which the line-protocol demo's controller uses.
"""

from __future__ import annotations

import asyncio
import re
import struct

# URScript's functions live with the demo's controller (robot_client.controllers): one copy,
# re-exported for the tests.
from robot_client.controllers.urscript import UR_MAX_NUMBERS as UR_MAX_NUMBERS
from robot_client.controllers.urscript import read_line as read_line
from robot_client.controllers.urscript import socket_read_ascii_float as socket_read_ascii_float

# ---------------------------------------------------------------------------- REAL numbers

_DECIMAL = re.compile(r"^[+-]?(\d+(\.\d*)?|\.\d+)([eE][+-]?\d+)?$")
"""A decimal number as RAPID's StrToVal (a ``num`` literal, with a sign), KRL's SREAD %f
and KAREL's CNV_STR_REAL accept it: no blanks, no thousands separators, ``.`` as the point."""
_INTEGER = re.compile(r"^[+-]?\d+$")


def real32(value: float) -> float:
    """``value`` as the controller holds it: RAPID ``num``, KRL and KAREL ``REAL`` are 32-bit
    floats (about 7 significant digits; integers exact up to 2**23)."""
    return float(struct.unpack("<f", struct.pack("<f", value))[0])


def _to_real(text: str) -> float | None:
    return real32(float(text)) if _DECIMAL.match(text) else None


# ---------------------------------------------------------------------------- ABB RAPID

RAPID_STRING_MAX = 80
"""Characters a RAPID ``string`` holds."""


async def rapid_receive_line(reader: asyncio.StreamReader, timeout_s: float = 12.0) -> str | None:
    """What examples/robots/abb/VisionCheck.mod does: ``SocketReceive \\Str`` (what has
    arrived, at most what still fits the 80-character string) appended to the answer until it
    holds a LF; None for a timeout, a closed socket, or an answer that outgrows the string
    (RAPID raises an error there)."""
    answer = b""
    try:
        async with asyncio.timeout(timeout_s):
            while b"\n" not in answer:
                room = RAPID_STRING_MAX - len(answer)
                if room <= 0:
                    return None
                part = await reader.read(room)
                if not part:
                    return None
                answer += part
    except TimeoutError:
        return None
    return answer.decode("ascii")


def rapid_fields(answer: str, count: int) -> list[float] | None:
    """The example's parse: cut the answer at its CR (StrFind ``"\\0D"``), take ``count``
    fields separated by ``,`` (StrFind, StrPart) and convert each with ``StrToVal``, which
    fails (returns FALSE) for anything that is not a whole num literal. None on any failure."""
    end = answer.find("\r")
    body = answer if end < 0 else answer[:end]
    parts = body.split(",")
    if len(parts) < count:
        return None
    values = [_to_real(part) for part in parts[:count]]
    return None if any(v is None for v in values) else [v for v in values if v is not None]


# ---------------------------------------------------------------------------- KUKA KRL (EKI)

EKI_STREAM_SIZE = 254
"""The ``Size`` of the stream element in examples/robots/kuka/VisionCheck.xml."""


async def eki_stream(
    reader: asyncio.StreamReader, size: int = EKI_STREAM_SIZE, timeout_s: float = 12.0
) -> str | None:
    """EthernetKRL's ``STREAM`` element with ``EOS="13,10"``: the bytes up to the end string,
    without it (what ``EKI_GetString`` copies out); None for a timeout, a closed socket, or a
    stream longer than the element's ``Size`` (EKI reports an overflow)."""
    try:
        async with asyncio.timeout(timeout_s):
            raw = await reader.readuntil(b"\r\n")
    except (TimeoutError, asyncio.IncompleteReadError, asyncio.LimitOverrunError):
        return None
    body = raw[:-2]
    return None if len(body) > size else body.decode("ascii")


def krl_sread(text: str, fmt: str) -> list[float] | None:
    """KRL's ``SREAD(text, state, offset, fmt, ...)`` with a format of ``%d`` and ``%f``
    separated by blanks: each conversion skips blanks, then takes the field; None (state
    ``RET1`` not ``CMD_OK``) when a field is missing or is not of its type. A ``%d`` field is an
    INT, a ``%f`` one a 32-bit REAL."""
    kinds = fmt.split()
    fields = text.split()
    if len(fields) < len(kinds):
        return None
    values: list[float] = []
    for kind, field in zip(kinds, fields, strict=False):
        if kind == "%d":
            if not _INTEGER.match(field):
                return None
            values.append(float(int(field)))
        elif kind == "%f":
            real = _to_real(field)
            if real is None:
                return None
            values.append(real)
        else:
            raise ValueError(f"the test client knows %d and %f, not {kind}")
    return values


# ---------------------------------------------------------------------------- FANUC KAREL

KAREL_FIELD = 12
"""Characters of each field of the ``fanuc`` format."""


async def karel_read(
    reader: asyncio.StreamReader, length: int, declared: int, timeout_s: float = 12.0
) -> str | None:
    """KAREL's ``READ file (answer::length)`` on a socket file with ``ATR_TIMEOUT``: exactly
    ``length`` characters, kept up to the STRING's ``declared`` length (the rest is cut on the
    right); None when the read times out or the socket closes (IO_STATUS not 0)."""
    try:
        async with asyncio.timeout(timeout_s):
            raw = await reader.readexactly(length)
    except (TimeoutError, asyncio.IncompleteReadError):
        return None
    return raw.decode("ascii")[:declared]


def karel_fields(answer: str, count: int) -> list[float] | None:
    """The example's parse: field i is ``SUB_STR(answer, 12 * (i - 1) + 1, 12)``, converted
    by ``CNV_STR_REAL``, which leaves its REAL uninitialized (None here) for a string that is
    not a number."""
    values: list[float] = []
    for i in range(count):
        real = _to_real(answer[KAREL_FIELD * i : KAREL_FIELD * (i + 1)])
        if real is None:
            return None
        values.append(real)
    return values
