"""Rigid transforms as 4x4 homogeneous matrices and rotation helpers.

Conventions (see docs/conventions.md): a transform named ``b_from_a`` maps points in
frame ``a`` to frame ``b`` (``p_b = b_from_a @ p_a``) and is the pose of ``a`` in ``b``.
Lengths are in metres, angles in radians, arrays are float64.

Roll-pitch-yaw: extrinsic rotations about the fixed X, then Y, then Z axes, which is
``R = Rz(yaw) @ Ry(pitch) @ Rx(roll)`` (the same matrix as intrinsic Z-Y'-X'').
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from numpy.typing import ArrayLike, NDArray

__all__ = [
    "invert_transform",
    "make_transform",
    "orthonormalize",
    "rotation_angle",
    "rotation_from_axis_angle",
    "rotation_from_rpy",
    "rpy_from_rotation",
    "transform_from_xyz_rpy",
    "transform_points",
    "xyz_rpy_from_transform",
]

FloatArray = NDArray[np.float64]


def _as_rotation(rotation: ArrayLike, name: str = "rotation") -> FloatArray:
    arr = np.asarray(rotation, dtype=np.float64)
    if arr.shape != (3, 3):
        raise ValueError(f"{name} must have shape (3, 3), got {arr.shape}")
    if not np.all(np.isfinite(arr)):
        raise ValueError(f"{name} must be finite")
    return arr


def _as_transform(transform: ArrayLike, name: str) -> FloatArray:
    arr = np.asarray(transform, dtype=np.float64)
    if arr.shape != (4, 4):
        raise ValueError(f"{name} must have shape (4, 4), got {arr.shape}")
    if not np.all(np.isfinite(arr)):
        raise ValueError(f"{name} must be finite")
    return arr


def make_transform(rotation: ArrayLike, translation: ArrayLike) -> FloatArray:
    """Build ``b_from_a`` (4, 4) from ``rotation`` (3, 3) and ``translation`` (3,) in metres.

    They are the orientation and the origin of frame ``a`` expressed in frame ``b``.
    """
    rot = _as_rotation(rotation)
    trans = np.asarray(translation, dtype=np.float64).reshape(-1)
    if trans.shape != (3,):
        raise ValueError(f"translation must have 3 elements, got shape {np.shape(translation)}")
    out = np.eye(4)
    out[:3, :3] = rot
    out[:3, 3] = trans
    return out


def invert_transform(b_from_a: ArrayLike) -> FloatArray:
    """Return ``a_from_b`` for a rigid ``b_from_a`` (uses R^T, not a general inverse)."""
    mat = _as_transform(b_from_a, "b_from_a")
    rot_t = mat[:3, :3].T
    out = np.eye(4)
    out[:3, :3] = rot_t
    out[:3, 3] = -rot_t @ mat[:3, 3]
    return out


def transform_points(b_from_a: ArrayLike, p_a: ArrayLike) -> FloatArray:
    """Map points ``p_a`` (N, 3) or (3,) in frame ``a`` to frame ``b``; same shape out."""
    mat = _as_transform(b_from_a, "b_from_a")
    pts = np.asarray(p_a, dtype=np.float64)
    if pts.shape[-1:] != (3,) or pts.ndim not in (1, 2):
        raise ValueError(f"p_a must have shape (N, 3) or (3,), got {pts.shape}")
    result: FloatArray = pts @ mat[:3, :3].T + mat[:3, 3]
    return result


def _rot_x(a: float) -> FloatArray:
    c, s = np.cos(a), np.sin(a)
    return np.array([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]])


def _rot_y(a: float) -> FloatArray:
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


def _rot_z(a: float) -> FloatArray:
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def rotation_from_rpy(roll: float, pitch: float, yaw: float) -> FloatArray:
    """``R = Rz(yaw) @ Ry(pitch) @ Rx(roll)`` (extrinsic X-Y-Z), angles in radians."""
    return _rot_z(float(yaw)) @ _rot_y(float(pitch)) @ _rot_x(float(roll))


def rpy_from_rotation(rotation: ArrayLike) -> tuple[float, float, float]:
    """Inverse of :func:`rotation_from_rpy`: ``(roll, pitch, yaw)`` in radians.

    pitch is in [-pi/2, pi/2], roll and yaw in (-pi, pi]. At gimbal lock (|pitch| = pi/2)
    roll is set to 0 and the whole rotation about z is put into yaw.
    """
    rot = _as_rotation(rotation)
    sp = -rot[2, 0]
    pitch = float(np.arcsin(np.clip(sp, -1.0, 1.0)))
    if abs(sp) > 1.0 - 1e-12:
        roll = 0.0
        # cos(pitch) = 0 couples roll and yaw; with roll = 0, R[0,1] = -sin(yaw), R[1,1] = cos(yaw).
        yaw = float(np.arctan2(-rot[0, 1], rot[1, 1]))
    else:
        roll = float(np.arctan2(rot[2, 1], rot[2, 2]))
        yaw = float(np.arctan2(rot[1, 0], rot[0, 0]))
    return roll, pitch, yaw


def rotation_from_axis_angle(axis: ArrayLike, angle: float) -> FloatArray:
    """Rotation by ``angle`` (radians, right-handed) about ``axis`` (3,), any non-zero length."""
    a = np.asarray(axis, dtype=np.float64).reshape(-1)
    if a.shape != (3,):
        raise ValueError(f"axis must have 3 elements, got shape {np.shape(axis)}")
    n = float(np.linalg.norm(a))
    if not np.isfinite(n) or n < 1e-12:
        raise ValueError("axis must be a finite non-zero vector")
    x, y, z = a / n
    skew = np.array([[0.0, -z, y], [z, 0.0, -x], [-y, x, 0.0]])
    s, c = np.sin(float(angle)), np.cos(float(angle))
    result: FloatArray = np.eye(3) + s * skew + (1.0 - c) * (skew @ skew)
    return result


def rotation_angle(rotation: ArrayLike) -> float:
    """Geodesic angle (radians, in [0, pi]) of ``rotation`` (3, 3).

    For the angle between two rotations ``r_a`` and ``r_b`` use ``rotation_angle(r_a.T @ r_b)``.
    """
    rot = _as_rotation(rotation)
    c = (np.trace(rot) - 1.0) / 2.0
    # Near 0 arccos is ill-conditioned; use the sine from the skew part as well.
    s = 0.5 * np.linalg.norm([rot[2, 1] - rot[1, 2], rot[0, 2] - rot[2, 0], rot[1, 0] - rot[0, 1]])
    return float(np.arctan2(s, np.clip(c, -1.0, 1.0)))


def orthonormalize(matrix: ArrayLike) -> FloatArray:
    """The rotation nearest to ``matrix`` (3, 3) in the Frobenius norm (via SVD, det = +1)."""
    m = _as_rotation(matrix, "matrix")
    u, _, vt = np.linalg.svd(m)
    fix = np.eye(3)
    fix[2, 2] = np.sign(np.linalg.det(u @ vt)) or 1.0
    result: FloatArray = u @ fix @ vt
    return result


def transform_from_xyz_rpy(
    xyz: Sequence[float] | ArrayLike, rpy: Sequence[float] | ArrayLike
) -> FloatArray:
    """Pose from a position ``xyz`` (metres) and ``rpy`` = (roll, pitch, yaw) in radians."""
    r = np.asarray(rpy, dtype=np.float64).reshape(-1)
    if r.shape != (3,):
        raise ValueError(f"rpy must have 3 elements, got shape {np.shape(rpy)}")
    return make_transform(rotation_from_rpy(r[0], r[1], r[2]), xyz)


def xyz_rpy_from_transform(b_from_a: ArrayLike) -> tuple[FloatArray, tuple[float, float, float]]:
    """Inverse of :func:`transform_from_xyz_rpy`: ``(xyz (3,), (roll, pitch, yaw))``."""
    mat = _as_transform(b_from_a, "b_from_a")
    return mat[:3, 3].copy(), rpy_from_rotation(mat[:3, :3])
