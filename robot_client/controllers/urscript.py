"""What a Universal Robots controller's URScript functions do with the line protocol
(protocol/LINE.md §5.2, §5.7).

:func:`socket_read_ascii_float` follows URScript's documented rules for the function of that
name: it reads ``number`` numbers written as ``(v1, v2, ...)`` and returns
``[count, v1, ..., vn]``; a read that fails (no list, a value that is not a number, another
count than asked for, more than 30) or times out returns ``[0, nan, ..., nan]``. Bytes before
the opening parenthesis are skipped (so the CR LF ending the previous answer is harmless).
:func:`pose_to_str` is ``to_str(p[...])`` of a pose, :func:`ur_pose` the pose ``p[x, y, z,
rx, ry, rz]`` (metres, rotation vector in radians) as the 4x4 ``base_from_tool`` it means.
"""

from __future__ import annotations

import asyncio
import math
import re
from collections.abc import Sequence

import numpy as np
from numpy.typing import NDArray

from geometry import make_transform, rotation_angle, rotation_from_axis_angle

__all__ = ["UR_MAX_NUMBERS", "pose_to_str", "read_line", "socket_read_ascii_float", "ur_pose"]

UR_MAX_NUMBERS = 30
_UR_NUMBER = re.compile(r"^[+-]?(\d+(\.\d*)?|\.\d+)([eE][+-]?\d+)?$")

Matrix = NDArray[np.float64]


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


def ur_pose(values: Sequence[float]) -> Matrix:
    """``p[x, y, z, rx, ry, rz]`` (metres; rotation vector, radians) as ``base_from_tool``."""
    x, y, z, rx, ry, rz = (float(v) for v in values)
    angle = math.sqrt(rx * rx + ry * ry + rz * rz)
    rotation = np.eye(3) if angle < 1e-12 else rotation_from_axis_angle([rx, ry, rz], angle)
    return make_transform(rotation, [x, y, z])


def pose_to_str(base_from_tool: Matrix) -> str:
    """URScript's ``to_str(get_actual_tcp_pose())``: ``p[x, y, z, rx, ry, rz]``."""
    rotation = base_from_tool[:3, :3]
    angle = rotation_angle(rotation)
    if angle < 1e-12:
        vector = np.zeros(3)
    elif angle > math.pi - 1e-6:  # a half turn: the axis is R + I's largest column
        sym = (rotation + np.eye(3)) / 2.0
        column = int(np.argmax(np.diag(sym)))
        axis = sym[:, column] / np.linalg.norm(sym[:, column])
        vector = axis * angle
    else:
        skew = np.array(
            [
                rotation[2, 1] - rotation[1, 2],
                rotation[0, 2] - rotation[2, 0],
                rotation[1, 0] - rotation[0, 1],
            ]
        )
        vector = skew / (2.0 * math.sin(angle)) * angle
    numbers = [*base_from_tool[:3, 3], *vector]
    return "p[" + ", ".join(f"{float(v):.6f}" for v in numbers) + "]"
