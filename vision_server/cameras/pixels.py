"""GenICam pixel formats -> the colour convention (uint8 gray or BGR): pure functions.

GenICam names Bayer patterns by their top-left 2x2 cell read row by row (BayerRG8 = R G / G
B); OpenCV's ``COLOR_BayerRGGB2BGR`` family uses the same reading (its older ``BayerBG``
names read the second row and would swap red and blue).
"""

from __future__ import annotations

from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray

__all__ = ["MONO_BITS", "convert_pixels"]

MONO_BITS = {"Mono8": 8, "Mono10": 10, "Mono12": 12, "Mono16": 16}
"""Significant bits of each unpacked mono format (10 to 16 bits arrive in 16-bit words)."""

_BAYER = {
    "BayerRG8": cv2.COLOR_BayerRGGB2BGR,
    "BayerGR8": cv2.COLOR_BayerGRBG2BGR,
    "BayerGB8": cv2.COLOR_BayerGBRG2BGR,
    "BayerBG8": cv2.COLOR_BayerBGGR2BGR,
}

_PACKED_COLOUR = ("RGB8", "BGR8")
"""Three bytes a pixel, in the order the name gives."""


def convert_pixels(
    data: NDArray[Any], *, pixel_format: str, width: int, height: int
) -> NDArray[np.uint8]:
    """A frame's payload ``data`` (the flat buffer of ``width`` x ``height`` pixels) in
    ``pixel_format`` -> (H, W) uint8 gray or (H, W, 3) uint8 BGR (RGB8 is reordered).

    Mono formats above 8 bits are scaled to 8 bits, rounded (the inspections work on 8-bit
    images); values beyond the format's range saturate at 255. Raises
    ``ValueError`` naming the cause for an unsupported format or a buffer of the wrong size.
    """
    pixels = width * height
    if pixel_format in MONO_BITS:
        bits = MONO_BITS[pixel_format]
        want = np.uint8 if bits == 8 else np.uint16
        flat = np.asarray(data).reshape(-1)
        if flat.dtype != want:
            flat = flat.view(want) if flat.dtype == np.uint8 else flat.astype(want)
        if flat.size != pixels:
            raise ValueError(
                f"a {pixel_format} frame of {width}x{height} has {pixels} pixels, "
                f"the buffer holds {flat.size}"
            )
        image = flat.reshape(height, width)
        if bits == 8:
            return np.array(image, dtype=np.uint8)
        # OpenCV scales, rounds and saturates in one pass: ten times numpy's clip-and-shift.
        scaled = cv2.convertScaleAbs(image, alpha=1.0 / (1 << (bits - 8)))
        return np.asarray(scaled, dtype=np.uint8)
    if pixel_format in _BAYER:
        flat = np.asarray(data, dtype=np.uint8).reshape(-1)
        if flat.size != pixels:
            raise ValueError(
                f"a {pixel_format} frame of {width}x{height} has {pixels} pixels, "
                f"the buffer holds {flat.size}"
            )
        bgr = cv2.cvtColor(flat.reshape(height, width), _BAYER[pixel_format])
        return np.asarray(bgr, dtype=np.uint8)
    if pixel_format in _PACKED_COLOUR:
        flat = np.asarray(data, dtype=np.uint8).reshape(-1)
        if flat.size != pixels * 3:
            raise ValueError(
                f"a {pixel_format} frame of {width}x{height} has {pixels * 3} bytes, "
                f"the buffer holds {flat.size}"
            )
        packed = flat.reshape(height, width, 3)
        if pixel_format == "RGB8":
            return np.ascontiguousarray(packed[:, :, ::-1])
        return np.array(packed, dtype=np.uint8)
    raise ValueError(
        f"pixel format {pixel_format!r} is not supported "
        f"(supported: {', '.join([*MONO_BITS, *_BAYER, *_PACKED_COLOUR])})"
    )
