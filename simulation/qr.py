"""QR symbol generation (OpenCV's encoder) and the fixed board-to-QR-frame rotation."""

from __future__ import annotations

from functools import lru_cache

import cv2
import numpy as np
from numpy.typing import NDArray

__all__ = ["BOARD_FROM_QR", "qr_modules"]

# Board frame: x right on the print, y up, z out of the print. QR frame (docs/conventions.md):
# x = (c0 - c3)/|..| = up, y = (c2 - c3)/|..| = right, z = x × y = into the print.
BOARD_FROM_QR: NDArray[np.float64] = np.array(
    [[0.0, 1.0, 0.0, 0.0], [1.0, 0.0, 0.0, 0.0], [0.0, 0.0, -1.0, 0.0], [0.0, 0.0, 0.0, 1.0]]
)


@lru_cache(maxsize=32)
def _modules_cached(text: str) -> bytes:
    encoder = cv2.QRCodeEncoder.create()
    image = encoder.encode(text)
    if image is None or image.size == 0:
        raise ValueError(f"text cannot be encoded as a QR code: {text!r}")
    dark = np.asarray(image) < 128
    rows = np.flatnonzero(dark.any(axis=1))
    cols = np.flatnonzero(dark.any(axis=0))
    # The encoder adds a quiet zone; the symbol is the bounding box of its dark modules
    # (the finder patterns reach all four sides).
    symbol = dark[rows[0] : rows[-1] + 1, cols[0] : cols[-1] + 1]
    n = symbol.shape[0]
    if symbol.shape != (n, n) or n < 21:
        raise ValueError(f"unexpected QR symbol shape {symbol.shape}")
    return bytes([n]) + np.packbits(symbol).tobytes()


def qr_modules(text: str) -> NDArray[np.bool_]:
    """The module matrix (n, n) of the QR code for ``text``, True = dark, row 0 at the top.

    No quiet zone; n = 21 + 4 * (version - 1).
    """
    raw = _modules_cached(text)
    n = raw[0]
    bits = np.unpackbits(np.frombuffer(raw[1:], dtype=np.uint8))[: n * n]
    return bits.reshape(n, n).astype(bool)
