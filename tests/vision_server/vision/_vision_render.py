"""Synthetic images with exact ground truth for the vision tests.

Anti-aliasing is by supersampling: the scene is evaluated at the centres of ``s x s`` sub-pixels
and averaged (``cv2.INTER_AREA``). Pixel convention of docs/conventions.md: the centre of the
top-left pixel is ``(0, 0)``, so pixel ``k`` covers ``[k - 0.5, k + 0.5]``.
"""

from __future__ import annotations

import cv2
import numpy as np
from numpy.typing import NDArray


def subpixel_grid(
    width: int, height: int, s: int
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Full-image (u, v) coordinates of the centres of the ``s``-times finer sub-pixels."""
    u = (np.arange(width * s) + 0.5) / s - 0.5
    v = (np.arange(height * s) + 0.5) / s - 0.5
    return np.meshgrid(u, v)


def downsample(fine: NDArray[np.float64], width: int, height: int) -> NDArray[np.float64]:
    return np.asarray(cv2.resize(fine, (width, height), interpolation=cv2.INTER_AREA), np.float64)


def to_uint8(img: NDArray[np.float64], rng: np.random.Generator, sigma: float) -> NDArray[np.uint8]:
    noisy = img + rng.normal(0.0, sigma, img.shape) if sigma > 0 else img
    return np.clip(np.round(noisy), 0, 255).astype(np.uint8)


def qr_modules(text: str) -> NDArray[np.bool_]:
    """The QR symbol of ``text`` (True = dark), without quiet zone, (N, N)."""
    enc = cv2.QRCodeEncoder.create()
    img = enc.encode(text)
    dark = np.argwhere(img < 128)
    lo, hi = dark.min(axis=0), dark.max(axis=0)
    return np.asarray(img[lo[0] : hi[0] + 1, lo[1] : hi[1] + 1] < 128)


def render_qr(
    modules: NDArray[np.bool_],
    corners: NDArray[np.float64],
    *,
    width: int,
    height: int,
    s: int = 4,
    dark: float = 30.0,
    light: float = 220.0,
    background: float = 120.0,
    quiet: int = 4,
) -> NDArray[np.float64]:
    """Render the symbol so that its outer corners c0..c3 land at ``corners`` (4, 2) (u, v).

    The symbol (module (i, j) covers [j, j+1] x [i, i+1] in module units, c0 at (0, 0), c1 at
    (N, 0), c2 at (N, N), c3 at (0, N)) is mapped by the homography fixed by the corners; a
    ``quiet`` zone of light modules surrounds it, ``background`` lies beyond.
    """
    n = modules.shape[0]
    src = np.array([[0, 0], [n, 0], [n, n], [0, n]], dtype=np.float64)
    h = _homography64(src, corners)
    hi = np.linalg.inv(h)
    uu, vv = subpixel_grid(width, height, s)
    den = hi[2, 0] * uu + hi[2, 1] * vv + hi[2, 2]
    mu = (hi[0, 0] * uu + hi[0, 1] * vv + hi[0, 2]) / den
    mv = (hi[1, 0] * uu + hi[1, 1] * vv + hi[1, 2]) / den
    j = np.floor(mu).astype(int)
    i = np.floor(mv).astype(int)
    out = np.full(uu.shape, background)
    in_quiet = (i >= -quiet) & (i < n + quiet) & (j >= -quiet) & (j < n + quiet) & (den > 0)
    out[in_quiet] = light
    inside = (i >= 0) & (i < n) & (j >= 0) & (j < n) & (den > 0)
    out[inside] = np.where(modules[i[inside], j[inside]], dark, light)
    return downsample(out, width, height)


def _homography64(src: NDArray[np.float64], dst: NDArray[np.float64]) -> NDArray[np.float64]:
    rows = []
    rhs = []
    for (x, y), (u, v) in zip(src, dst, strict=True):
        rows.append([x, y, 1, 0, 0, 0, -u * x, -u * y])
        rhs.append(u)
        rows.append([0, 0, 0, x, y, 1, -v * x, -v * y])
        rhs.append(v)
    p = np.linalg.solve(np.array(rows), np.array(rhs))
    return np.append(p, 1.0).reshape(3, 3)


def disc_coverage(
    centre: tuple[float, float], radius: float, *, width: int, height: int, s: int = 8
) -> NDArray[np.float64]:
    """Fraction (0..1) of each pixel covered by the disc, by ``s x s`` supersampling.

    Only the disc's bounding box is supersampled (block means of whole pixels are exact).
    """
    cu, cv = centre
    out = np.zeros((height, width))
    u0, u1 = max(int(np.floor(cu - radius - 2)), 0), min(int(np.ceil(cu + radius + 2)), width)
    v0, v1 = max(int(np.floor(cv - radius - 2)), 0), min(int(np.ceil(cv + radius + 2)), height)
    if u1 <= u0 or v1 <= v0:
        return out
    uu = (np.arange(u0 * s, u1 * s) + 0.5) / s - 0.5
    vv = (np.arange(v0 * s, v1 * s) + 0.5) / s - 0.5
    inside = ((uu[None, :] - cu) ** 2 + (vv[:, None] - cv) ** 2 <= radius * radius).astype(float)
    out[v0:v1, u0:u1] = inside.reshape(v1 - v0, s, u1 - u0, s).mean(axis=(1, 3))
    return out


def render_discs(
    centres: NDArray[np.float64],
    radii: NDArray[np.float64],
    *,
    width: int,
    height: int,
    s: int = 8,
    fg: float = 200.0,
    bg: float = 50.0,
) -> NDArray[np.float64]:
    """Discs of grey ``fg`` on a ``bg`` background, anti-aliased by supersampling."""
    img = np.full((height, width), float(bg))
    for (cu, cv), r in zip(centres, radii, strict=True):
        cov = disc_coverage((float(cu), float(cv)), float(r), width=width, height=height, s=s)
        img = img * (1.0 - cov) + fg * cov
    return img


def kinect_depth_frames(
    normal: NDArray[np.float64],
    d: float,
    *,
    fx: float,
    fy: float,
    cx: float,
    cy: float,
    width: int,
    height: int,
    n_frames: int,
    rng: np.random.Generator,
    fb_px_m: float = 43.5,
    disparity_sigma_px: float = 0.06,
    disparity_step_px: float = 1.0 / 8.0,
    region: tuple[int, int, int, int] | None = None,
) -> list[NDArray[np.uint16]]:
    """Depth frames (uint16 mm) of the plane ``normal . p + d = 0`` seen by an undistorted camera.

    Kinect-like noise: disparity ``f*b / z`` plus Gaussian noise (``disparity_sigma_px``),
    quantised to ``disparity_step_px``, converted back to z and rounded to millimetres. At 1 m
    this gives a z sigma of about 1.4 mm (plus the quantisation steps, ~2.9 mm at 1 m).
    Only ``region`` ``(u0, v0, u1, v1)`` is rendered (0 = no depth elsewhere), to save time.
    """
    u0, v0, u1, v1 = (0, 0, width, height) if region is None else region
    full = np.zeros((height, width), np.uint16)
    uu, vv = np.meshgrid(np.arange(u0, u1, dtype=np.float64), np.arange(v0, v1, dtype=np.float64))
    x, y = (uu - cx) / fx, (vv - cy) / fy
    denom = normal[0] * x + normal[1] * y + normal[2]
    z = -d / denom
    frames = []
    for _ in range(n_frames):
        disparity = fb_px_m / z + rng.normal(0.0, disparity_sigma_px, z.shape)
        disparity = np.round(disparity / disparity_step_px) * disparity_step_px
        z_noisy = fb_px_m / disparity
        frame = full.copy()
        frame[v0:v1, u0:u1] = np.clip(np.round(z_noisy * 1000.0), 0, 65535).astype(np.uint16)
        frames.append(frame)
    return frames
