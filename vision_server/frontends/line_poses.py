"""Base-frame poses in each controller's own units and rotation convention (protocol/LINE.md
§5.7), both ways: what a trigger's answer sends, and the TCP pose a robot with a tool camera
sends with its trigger. A program moves to what it receives, and reports where it is, with its
controller's own pose type and no conversion:

========  ==========  ===========================================================
format    position    rotation
========  ==========  ===========================================================
``ur``    metres      rotation vector ``rx ry rz`` (radians), URScript's ``p[...]``
``abb``   mm          quaternion ``q1 q2 q3 q4`` (q1 the scalar), a robtarget's ``rot``
``kuka``  mm          ``A B C`` (degrees): Z, then the new Y, then the new X
``fanuc`` mm          ``W P R`` (degrees): about the fixed X, Y, Z axes
``text``  mm          ``W P R`` as FANUC's
========  ==========  ===========================================================

KUKA's A, B, C and FANUC's W, P, R describe the same matrix, ``Rz(A=R) Ry(B=P) Rx(C=W)``,
written in opposite orders.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from geometry import make_transform, rotation_from_axis_angle, rotation_from_rpy, rpy_from_rotation
from protocol import InvalidArgument

__all__ = ["CONVENTIONS", "Matrix", "PoseConvention", "parse_pose", "pose_values"]

Matrix = NDArray[np.float64]


@dataclass(frozen=True)
class PoseConvention:
    """One controller's pose: ``scale`` (metres -> its length unit), the names of its
    rotation values, the decimals of positions and rotations."""

    scale: float
    rotation: tuple[str, ...]
    position_decimals: int
    rotation_decimals: int

    @property
    def count(self) -> int:
        """Numbers a pose is written with."""
        return 3 + len(self.rotation)


_DEG = 180.0 / math.pi

CONVENTIONS: dict[str, PoseConvention] = {
    "text": PoseConvention(1000.0, ("w", "p", "r"), 2, 3),
    "ur": PoseConvention(1.0, ("rx", "ry", "rz"), 5, 5),
    "abb": PoseConvention(1000.0, ("q1", "q2", "q3", "q4"), 2, 6),
    "kuka": PoseConvention(1000.0, ("a", "b", "c"), 2, 3),
    "fanuc": PoseConvention(1000.0, ("w", "p", "r"), 2, 3),
}
"""Each answer format's pose convention (see the module)."""


def _rotation_vector(rotation: Matrix) -> list[float]:
    """Axis times angle (radians), the angle in [0, pi]."""
    cos = np.clip((np.trace(rotation) - 1.0) / 2.0, -1.0, 1.0)
    angle = float(np.arccos(cos))
    if angle < 1e-9:
        return [0.0, 0.0, 0.0]
    if angle > math.pi - 1e-6:
        # Near a half turn the skew part vanishes: take the axis from R + I's largest column.
        sym = (rotation + np.eye(3)) / 2.0
        column = int(np.argmax(np.diag(sym)))
        axis = sym[:, column] / math.sqrt(max(sym[column, column], 1e-12))
        return [float(a) * angle for a in axis / np.linalg.norm(axis)]
    skew = np.array(
        [
            rotation[2, 1] - rotation[1, 2],
            rotation[0, 2] - rotation[2, 0],
            rotation[1, 0] - rotation[0, 1],
        ]
    )
    return [float(a) for a in skew / (2.0 * math.sin(angle)) * angle]


def _quaternion(rotation: Matrix) -> list[float]:
    """``(w, x, y, z)`` with ``w >= 0`` (ABB's q1..q4). Computed from the largest of the four
    squared components (Shepperd's method), which is well conditioned for every rotation."""
    r = rotation
    squares = [
        1.0 + r[0, 0] + r[1, 1] + r[2, 2],
        1.0 + r[0, 0] - r[1, 1] - r[2, 2],
        1.0 - r[0, 0] + r[1, 1] - r[2, 2],
        1.0 - r[0, 0] - r[1, 1] + r[2, 2],
    ]
    k = int(np.argmax(squares))
    big = math.sqrt(squares[k]) / 2.0
    f = 1.0 / (4.0 * big)
    if k == 0:
        q = [big, (r[2, 1] - r[1, 2]) * f, (r[0, 2] - r[2, 0]) * f, (r[1, 0] - r[0, 1]) * f]
    elif k == 1:
        q = [(r[2, 1] - r[1, 2]) * f, big, (r[0, 1] + r[1, 0]) * f, (r[0, 2] + r[2, 0]) * f]
    elif k == 2:
        q = [(r[0, 2] - r[2, 0]) * f, (r[0, 1] + r[1, 0]) * f, big, (r[1, 2] + r[2, 1]) * f]
    else:
        q = [(r[1, 0] - r[0, 1]) * f, (r[0, 2] + r[2, 0]) * f, (r[1, 2] + r[2, 1]) * f, big]
    sign = -1.0 if q[0] < 0 else 1.0
    return [sign * float(v) for v in q]


def _rotation_values(fmt: str, rotation: Matrix) -> list[float]:
    if fmt == "ur":
        return _rotation_vector(rotation)
    if fmt == "abb":
        return _quaternion(rotation)
    roll, pitch, yaw = rpy_from_rotation(rotation)
    if fmt == "kuka":
        return [yaw * _DEG, pitch * _DEG, roll * _DEG]
    return [roll * _DEG, pitch * _DEG, yaw * _DEG]


def pose_values(fmt: str, base_from_x: Matrix) -> list[tuple[float, int]]:
    """``(value, decimals)`` of a pose (4x4, metres) in format ``fmt``'s convention."""
    convention = CONVENTIONS[fmt]
    position = [float(v) * convention.scale for v in base_from_x[:3, 3]]
    rotation = _rotation_values(fmt, base_from_x[:3, :3])
    return [(v, convention.position_decimals) for v in position] + [
        (v, convention.rotation_decimals) for v in rotation
    ]


def parse_pose(fmt: str, words: Sequence[str]) -> Matrix:
    """The TCP pose a trigger carries (the words after its inspection), in ``fmt``'s
    convention, as a 4x4 ``base_from_tool`` in metres. Numbers are separated by blanks or
    commas; URScript's ``p[...]`` (``to_str(get_actual_tcp_pose())``) and brackets are
    accepted. Raises INVALID_ARGUMENT naming what is wrong."""
    convention = CONVENTIONS[fmt]
    text = " ".join(words).replace("p[", " ").replace("[", " ").replace("]", " ")
    parts = text.replace(",", " ").split()
    names = "x y z " + " ".join(convention.rotation)
    if len(parts) != convention.count:
        raise InvalidArgument(
            f"a {fmt} pose is {convention.count} numbers ({names}), got {len(parts)}"
        )
    try:
        numbers = [float(p) for p in parts]
    except ValueError:
        raise InvalidArgument(f"the pose {text.strip()!r} is not {names} numbers") from None
    if not all(math.isfinite(n) for n in numbers):
        raise InvalidArgument("the pose has a value that is not a finite number")
    position = [n / convention.scale for n in numbers[:3]]
    r = numbers[3:]
    if fmt == "ur":
        angle = math.sqrt(sum(v * v for v in r))
        rotation = np.eye(3) if angle < 1e-12 else rotation_from_axis_angle(r, angle)
    elif fmt == "abb":
        rotation = _from_quaternion(r)
    elif fmt == "kuka":
        rotation = rotation_from_rpy(r[2] / _DEG, r[1] / _DEG, r[0] / _DEG)
    else:
        rotation = rotation_from_rpy(r[0] / _DEG, r[1] / _DEG, r[2] / _DEG)
    return make_transform(rotation, position)


def _from_quaternion(q: Sequence[float]) -> Matrix:
    norm = math.sqrt(sum(v * v for v in q))
    if not 0.9 < norm < 1.1:
        raise InvalidArgument(f"the quaternion q1..q4 has length {norm:.3f}, not 1")
    w, x, y, z = (v / norm for v in q)
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
            [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
            [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
        ]
    )
