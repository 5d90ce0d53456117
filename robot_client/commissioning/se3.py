"""Small rotations and pose changes for the commissioning solvers (4x4 ``b_from_a``, radians,
metres; docs/conventions.md)."""

from __future__ import annotations

import cv2
import numpy as np
from numpy.typing import NDArray

from geometry import make_transform

FloatArray = NDArray[np.float64]

__all__ = ["exp_rotation", "log_rotation", "perturbed"]


def log_rotation(rotation: FloatArray) -> FloatArray:
    """Axis times angle of ``rotation`` (radians)."""
    rvec, _ = cv2.Rodrigues(np.asarray(rotation, dtype=np.float64))
    return np.asarray(rvec, dtype=np.float64).reshape(3)


def exp_rotation(rvec: FloatArray) -> FloatArray:
    """The rotation of axis-angle vector ``rvec`` (any length, zero included)."""
    rotation, _ = cv2.Rodrigues(np.asarray(rvec, dtype=np.float64).reshape(3, 1))
    return np.asarray(rotation, dtype=np.float64)


def perturbed(transform: FloatArray, delta: FloatArray) -> FloatArray:
    """``transform`` moved by ``delta`` = (rotation vector applied on the left, translation):
    the coordinates in which the solvers' Jacobians and covariances are written."""
    rotation = exp_rotation(delta[:3]) @ transform[:3, :3]
    return make_transform(rotation, transform[:3, 3] + delta[3:])
