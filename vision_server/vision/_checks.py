"""Input validation shared by the inspections (typed errors that name the cause)."""

from __future__ import annotations

from collections.abc import Sequence

import cv2
import numpy as np
from numpy.typing import NDArray

from vision_server.vision.errors import BadImageError, ParameterError, RoiError

__all__ = ["Roi", "as_gray", "check_depth", "check_image", "check_roi", "crop"]

Roi = tuple[int, int, int, int]
"""A region of interest ``(u, v, width, height)`` in full-image pixels."""


def check_image(image: object, *, name: str = "image") -> NDArray[np.uint8]:
    """Check that ``image`` is a gray ``(H, W)`` or BGR ``(H, W, 3)`` uint8 array.

    A single-channel ``(H, W, 1)`` array is accepted and squeezed to ``(H, W)``.

    Raises
    ------
    BadImageError
        Not an ndarray, wrong dtype, wrong number of dimensions or channels, or empty.
    """
    if not isinstance(image, np.ndarray):
        raise BadImageError(f"{name} must be a numpy array, got {type(image).__name__}")
    if image.dtype != np.uint8:
        raise BadImageError(f"{name} must be uint8, got dtype {image.dtype}")
    if image.ndim == 3 and image.shape[2] == 1:
        image = image[:, :, 0]
    if image.ndim == 3:
        if image.shape[2] != 3:
            raise BadImageError(
                f"{name} must be gray (H, W) or BGR (H, W, 3), got {image.shape[2]} channels"
            )
    elif image.ndim != 2:
        raise BadImageError(f"{name} must have 2 or 3 dimensions, got shape {image.shape}")
    if image.shape[0] == 0 or image.shape[1] == 0:
        raise BadImageError(f"{name} is empty (shape {image.shape})")
    return image


def as_gray(image: object, *, name: str = "image") -> NDArray[np.uint8]:
    """Validate ``image`` (see :func:`check_image`) and return it as gray uint8 ``(H, W)``."""
    img = check_image(image, name=name)
    if img.ndim == 3:
        return np.asarray(cv2.cvtColor(img, cv2.COLOR_BGR2GRAY), dtype=np.uint8)
    return np.ascontiguousarray(img)


def check_depth(depth: object, *, name: str = "depth") -> NDArray[np.uint16]:
    """Check that ``depth`` is a ``(H, W)`` uint16 depth image in millimetres (0 = no depth)."""
    if not isinstance(depth, np.ndarray):
        raise BadImageError(f"{name} must be a numpy array, got {type(depth).__name__}")
    if depth.dtype != np.uint16:
        raise BadImageError(f"{name} must be uint16 millimetres, got dtype {depth.dtype}")
    if depth.ndim == 3 and depth.shape[2] == 1:
        depth = depth[:, :, 0]
    if depth.ndim != 2:
        raise BadImageError(f"{name} must have shape (H, W), got {depth.shape}")
    if depth.size == 0:
        raise BadImageError(f"{name} is empty (shape {depth.shape})")
    return depth


def check_roi(roi: Sequence[float] | None, shape: tuple[int, ...]) -> Roi:
    """Check an ROI ``[u, v, width, height]`` against an image of ``shape`` ``(H, W[, C])``.

    ``None`` means the whole image. Values must be integers (floats with an integral value are
    accepted).

    Raises
    ------
    RoiError
        Wrong length, non-integral or non-positive size, or not entirely inside the image.
    """
    height, width = int(shape[0]), int(shape[1])
    if roi is None:
        return (0, 0, width, height)
    try:
        values = [float(x) for x in roi]
    except (TypeError, ValueError) as exc:
        raise RoiError(f"roi must be 4 numbers [u, v, width, height], got {roi!r}") from exc
    if len(values) != 4:
        raise RoiError(f"roi must be 4 numbers [u, v, width, height], got {len(values)} values")
    if not all(np.isfinite(values)) or any(x != round(x) for x in values):
        raise RoiError(f"roi must be whole pixels, got {roi!r}")
    u, v, w, h = (round(x) for x in values)
    if w <= 0 or h <= 0:
        raise RoiError(f"roi width and height must be positive, got {w}x{h}")
    if u < 0 or v < 0 or u + w > width or v + h > height:
        raise RoiError(
            f"roi [u={u}, v={v}, width={w}, height={h}] is not inside the {width}x{height} image"
        )
    return (u, v, w, h)


def crop(image: NDArray[np.generic], roi: Roi) -> NDArray[np.generic]:
    """The ``roi`` (already checked) of ``image``: a view, rows ``v:v+h``, columns ``u:u+w``."""
    u, v, w, h = roi
    return image[v : v + h, u : u + w]


def check_positive(value: float, name: str) -> float:
    """``value`` as a float if it is finite and > 0, else a :class:`ParameterError`."""
    out = float(value)
    if not np.isfinite(out) or out <= 0:
        raise ParameterError(f"{name} must be a positive number, got {value!r}")
    return out


def check_range(lo: float, hi: float, name: str) -> tuple[float, float]:
    """``(lo, hi)`` as floats if finite and ``lo <= hi``, else a :class:`ParameterError`."""
    a, b = float(lo), float(hi)
    if not (np.isfinite(a) and np.isfinite(b)) or a > b:
        raise ParameterError(f"{name} must be a finite range (min <= max), got ({lo!r}, {hi!r})")
    return a, b
