"""Sensor models: grey-level noise, vignetting, blur, and structured-light depth.

Depth follows the Kinect / Xtion model of Khoshelham & Elberink (2012): the sensor measures a
disparity d = fb / z (px); d carries Gaussian noise (``disparity_sigma_px``, about 0.06 px) and
is quantised to 1/8 px; z = fb / d. With fb = 43.5 px m this gives sigma_z = z^2 / fb * sigma_d
(1.4 mm at 1 m) and steps of z^2 / (8 fb) (2.9 mm at 1 m). Depth is z along the optical axis in
millimetres (uint16, 0 = no depth), registered to the colour pixels unless
``misregistration_px`` is set.
"""

from __future__ import annotations

import cv2
import numpy as np
from numpy.typing import NDArray

from simulation.scene import DepthSpec

__all__ = ["NoiseBank", "depth_image", "vignette_map"]

BANK_PAD = 96


class NoiseBank:
    """Precomputed standard-normal noise, read at a random offset per frame.

    Drawing fresh Gaussian noise for a megapixel frame costs more than rendering it; a bank
    (BANK_PAD more rows and columns than the image) read at a random offset from the frame's
    generator gives frames whose noise is independent for practical purposes.
    """

    def __init__(self, rng: np.random.Generator, shape: tuple[int, ...]) -> None:
        h, w = shape[:2]
        self._bank = rng.standard_normal((h + BANK_PAD, w + BANK_PAD, *shape[2:]), np.float32)
        self.shape = shape
        self._u8: dict[float, NDArray[np.uint8]] = {}

    def take(self, rng: np.random.Generator) -> NDArray[np.float32]:
        """A (shape) view of unit-variance noise at a random offset."""
        dy, dx = rng.integers(0, BANK_PAD + 1, size=2)
        h, w = self.shape[:2]
        return self._bank[dy : dy + h, dx : dx + w]

    def take_u8(self, rng: np.random.Generator, sigma: float) -> NDArray[np.uint8]:
        """Noise as uint8 centred on 128 with standard deviation ``sigma`` grey levels."""
        bank = self._u8.get(sigma)
        if bank is None:
            bank = np.clip(np.rint(128.0 + sigma * self._bank), 0, 255).astype(np.uint8)
            self._u8[sigma] = bank
        dy, dx = rng.integers(0, BANK_PAD + 1, size=2)
        h, w = self.shape[:2]
        return bank[dy : dy + h, dx : dx + w]


def vignette_map(
    width: int, height: int, cx: float, cy: float, strength: float
) -> NDArray[np.uint8]:
    """Brightness factor * 255 (H, W): 1 at the principal point, 1 - strength at the corners."""
    v, u = np.mgrid[0:height, 0:width].astype(np.float32)
    r2 = (u - cx) ** 2 + (v - cy) ** 2
    r2max = max((0 - cx) ** 2, (width - 1 - cx) ** 2) + max((0 - cy) ** 2, (height - 1 - cy) ** 2)
    factor = 1.0 - strength * r2 / r2max
    result: NDArray[np.uint8] = np.clip(np.rint(factor * 255.0), 0, 255).astype(np.uint8)
    return result


def depth_image(
    z_true_m: NDArray[np.float32],
    spec: DepthSpec,
    rng: np.random.Generator,
    bank: NoiseBank,
) -> NDArray[np.uint16]:
    """Measured depth (H, W) uint16 mm from the true z-depth (NaN = nothing there)."""
    z = z_true_m.astype(np.float32) * np.float32(1.0 + spec.scale_bias)
    valid = np.isfinite(z) & (z > 0)
    z_safe = np.where(valid, z, np.float32(1.0))
    disparity = np.float32(spec.fb_px_m) / z_safe
    if spec.disparity_sigma_px > 0:
        disparity = disparity + np.float32(spec.disparity_sigma_px) * bank.take(rng)
    steps = np.float32(spec.subpixel_steps)
    disparity = np.rint(disparity * steps) / steps
    valid &= disparity > 0
    z_meas = np.float32(spec.fb_px_m) / np.where(valid, disparity, np.float32(1.0))
    valid &= (z_meas >= spec.range_m[0]) & (z_meas <= spec.range_m[1])

    # Structured light loses the pattern at depth discontinuities: invalidate both sides.
    zt = np.where(np.isfinite(z_true_m), z_true_m, np.float32(0.0)).astype(np.float32)
    jump = np.zeros(zt.shape, bool)
    limit = np.float32(spec.edge_jump_m) + np.float32(spec.edge_jump_rel) * zt
    dv = np.abs(np.diff(zt, axis=0)) > np.minimum(limit[1:], limit[:-1])
    du = np.abs(np.diff(zt, axis=1)) > np.minimum(limit[:, 1:], limit[:, :-1])
    jump[1:] |= dv
    jump[:-1] |= dv
    jump[:, 1:] |= du
    jump[:, :-1] |= du
    valid &= ~jump
    if spec.dropout > 0:
        valid &= rng.random(zt.shape, dtype=np.float32) >= spec.dropout

    out = np.where(valid, np.rint(z_meas * 1000.0), 0.0)
    depth = np.clip(out, 0, 65535).astype(np.uint16)
    du_px, dv_px = spec.misregistration_px
    if du_px or dv_px:
        shift = np.array([[1.0, 0.0, du_px], [0.0, 1.0, dv_px]])
        h, w = depth.shape
        depth = np.asarray(
            cv2.warpAffine(
                depth, shift, (w, h), flags=cv2.INTER_NEAREST, borderMode=cv2.BORDER_CONSTANT
            ),
            dtype=np.uint16,
        )
    return depth
