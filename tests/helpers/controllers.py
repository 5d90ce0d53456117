"""Test clients that read the line protocol's answers exactly as robot controllers do.

:func:`socket_read_ascii_float` follows URScript's documented rules for the function of that
name: it reads ``number`` numbers written as ``(v1, v2, ...)`` and returns
``[count, v1, ..., vn]``; a read that fails (no list, a value that is not a number, another
count than asked for, more than 30) or times out returns ``[0, nan, ..., nan]``. Bytes before
the opening parenthesis are skipped (so the CR LF ending the previous answer is harmless).
"""

from __future__ import annotations

import asyncio
import math
import re

UR_MAX_NUMBERS = 30
_UR_NUMBER = re.compile(r"^[+-]?(\d+(\.\d*)?|\.\d+)([eE][+-]?\d+)?$")


def _failed(number: int) -> list[float]:
    return [0.0] + [math.nan] * number


async def socket_read_ascii_float(
    reader: asyncio.StreamReader, number: int, timeout_s: float = 2.0
) -> list[float]:
    """URScript's ``socket_read_ascii_float(number, timeout=timeout_s)`` over ``reader``."""
    if not 1 <= number <= UR_MAX_NUMBERS:
        return _failed(number)
    try:
        async with asyncio.timeout(timeout_s):
            while (await reader.readexactly(1)) != b"(":
                pass
            body = await reader.readuntil(b")")
    except (TimeoutError, asyncio.IncompleteReadError, asyncio.LimitOverrunError):
        return _failed(number)
    parts = body[:-1].decode("ascii", "replace").split(",")
    values: list[float] = []
    for part in parts:
        text = part.strip()
        if not _UR_NUMBER.match(text):
            return _failed(number)
        values.append(float(text))
    if len(values) != number:
        return _failed(number)
    return [float(number), *values]


async def read_line(reader: asyncio.StreamReader, timeout_s: float = 10.0) -> str:
    """One answer line as URScript's ``socket_read_line`` returns it: up to LF, without the
    LF or CR LF; "" when the connection ended."""
    async with asyncio.timeout(timeout_s):
        raw = await reader.readline()
    return raw.decode("ascii").rstrip("\r\n")
