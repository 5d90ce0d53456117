"""Print-quality estimates of a read code (:class:`Grade`) and its polarity, from the grey
image and the symbol's corners: the grading half of :mod:`vision_server.analysis.codes`."""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
from numpy.typing import NDArray

__all__ = ["Grade", "grade_code", "is_inverted"]

FloatArray = NDArray[np.float64]
GrayImage = NDArray[np.uint8]


@dataclass(frozen=True)
class Grade:
    """Print-quality estimates of one read code, from the grey image.

    - ``module_px``: the module (narrowest bar or cell) size in pixels: for a matrix code, the
      mean side of the corner quadrilateral divided by the modules per side that the decoder
      reports (its version); otherwise the median of the runs no longer than 1.5x the shortest
      runs on the scan line through the symbol's middle (c0c3 midpoint to c1c2 midpoint),
      thresholded at the mid-level.
    - ``contrast``: (light - dark) / 255, light and dark the 90th and 10th percentiles of the
      grey values of the pixels inside the corner quadrilateral (of the scan line where that
      holds fewer than 50 pixels, as a 1D code's may) (0..1; ISO's symbol contrast in spirit).
    - ``decode_margin``: the median over the same pixels of ``|g - mid| / ((light - dark) /
      2)``, ``mid`` = (light + dark) / 2, clipped to 0..1: 1 when every pixel is fully light or
      fully dark, 0 when all sit at the threshold (blur, low contrast, noise and ink spread
      lower it; module edges take a few pixels even in a sharp image).
    - ``quiet_zone_modules``: the smallest, over the four sides, of the width of the uniform
      background beside the symbol, in modules: along the outward normal at the side's middle,
      the distance to the first pixel further than half the contrast from the background level
      (the median just outside the symbol), plus the half module skipped at the start;
      searched up to 10 modules (``10.0`` = at least) and up to the image edge (a zone cut
      by the edge counts what is seen). ``None`` where a side lies on the image edge.
    """

    module_px: float
    contrast: float
    decode_margin: float
    quiet_zone_modules: float | None


def _modules_per_side(symbology: str, version: str | None) -> float | None:
    """Modules along a side of a matrix symbol from the decoder's version string."""
    if version is None:
        return None
    try:
        if symbology == "datamatrix":  # "ROWSxCOLUMNS"
            rows, cols = (int(x) for x in version.lower().split("x"))
            return (rows + cols) / 2.0
        number = int(version)
    except ValueError:
        return None
    if symbology == "qr":
        return 17.0 + 4.0 * number
    if symbology == "micro_qr":
        return 9.0 + 2.0 * number
    return None  # Aztec's size depends on compact/full as well: measured instead


def _profile(gray: GrayImage, a: FloatArray, b: FloatArray) -> NDArray[np.float32]:
    n = int(np.clip(np.linalg.norm(b - a) * 2.0, 8, 4000))  # two samples per pixel
    t = np.linspace(0.0, 1.0, n)
    pts = a[None, :] + t[:, None] * (b - a)[None, :]
    mx = pts[:, 0].astype(np.float32).reshape(1, -1)
    my = pts[:, 1].astype(np.float32).reshape(1, -1)
    prof = cv2.remap(gray, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
    return np.asarray(prof, np.float32).reshape(-1)


def grade_code(gray: GrayImage, quad: FloatArray, symbology: str, version: str | None) -> Grade:
    """The :class:`Grade` of the symbol with corners ``quad`` (4, 2) pixels of ``gray``;
    ``version``: the decoder's size string (QR's version, DataMatrix's ROWSxCOLUMNS) or None."""
    height, width = gray.shape
    mask = np.zeros(gray.shape, np.uint8)
    cv2.fillConvexPoly(mask, np.round(quad).astype(np.int32), 1)
    left = (quad[0] + quad[3]) / 2.0
    right = (quad[1] + quad[2]) / 2.0
    prof = _profile(gray, left, right)
    inside = gray[mask > 0].astype(np.float32)
    # a 1D code's corners may enclose a thin band only: then its scan line is the sample
    samples = inside if inside.size >= 50 else prof
    light = float(np.percentile(samples, 90))
    dark = float(np.percentile(samples, 10))
    contrast = (light - dark) / 255.0
    mid = (light + dark) / 2.0
    half = max((light - dark) / 2.0, 1e-6)
    margin = float(np.clip(np.median(np.abs(samples - mid) / half), 0.0, 1.0))
    sides = np.linalg.norm(quad - np.roll(quad, -1, axis=0), axis=1)
    modules = _modules_per_side(symbology, version)
    if modules is not None:
        module = float(np.mean(sides) / modules)
    else:
        module = _narrow_run_px(prof, mid, float(np.linalg.norm(right - left)))
    quiet = _quiet_zone(gray, quad, module, contrast * 255.0, width, height)
    return Grade(module, contrast, margin, quiet)


def _narrow_run_px(prof: NDArray[np.float32], mid: float, length_px: float) -> float:
    dark = prof < mid
    change = np.flatnonzero(np.diff(dark.astype(np.int8))) + 1
    runs = np.diff(np.concatenate([[0], change, [dark.size]]))[1:-1]  # whole runs only
    if runs.size == 0:
        return length_px
    px_per_sample = length_px / max(prof.size - 1, 1)
    shortest = float(np.percentile(runs, 10))
    narrow = runs[runs <= 1.5 * shortest]
    return float(np.median(narrow)) * px_per_sample


def _quiet_zone(
    gray: GrayImage, quad: FloatArray, module: float, contrast: float, width: int, height: int
) -> float | None:
    if module <= 0:
        return None
    centre = quad.mean(axis=0)
    reach = 10.0 * module
    widths = []
    for i in range(4):
        a, b = quad[i], quad[(i + 1) % 4]
        mid_side = (a + b) / 2.0
        d = b - a
        length = float(np.linalg.norm(d))
        if length < 1e-6:
            continue
        normal = np.array([d[1], -d[0]]) / length
        if normal @ (mid_side - centre) < 0:
            normal = -normal
        # start half a module out: the corner estimate may lie on the symbol's edge
        start = mid_side + 0.5 * module * normal
        if not (0 <= start[0] <= width - 1 and 0 <= start[1] <= height - 1):
            return None  # the symbol touches the image edge: no quiet zone to see
        # stop at the image edge: beyond it the width is unknown, so it counts as seen so far
        room = _room(start, normal, width, height)
        end = start + min(reach - 0.5 * module, room) * normal
        prof = _profile(gray, start, end)
        background = float(np.median(prof[: max(2, prof.size // 20)]))
        off = np.flatnonzero(np.abs(prof - background) > contrast / 2.0)
        span = float(np.linalg.norm(end - start))
        distance = span if off.size == 0 else span * off[0] / max(prof.size - 1, 1)
        widths.append((distance + 0.5 * module) / module)
    return float(min(widths)) if widths else None


def _room(p: FloatArray, direction: FloatArray, width: int, height: int) -> float:
    """Distance from ``p`` along unit ``direction`` to the image's last pixel centre."""
    limits = []
    for k, size in ((0, width), (1, height)):
        if direction[k] > 1e-9:
            limits.append((size - 1 - p[k]) / direction[k])
        elif direction[k] < -1e-9:
            limits.append(-p[k] / direction[k])
    return float(max(0.0, min(limits))) if limits else 0.0


def is_inverted(gray: GrayImage, quad: FloatArray) -> bool:
    """Light-on-dark: the ring just outside the symbol is darker than the symbol's mean."""
    centre = quad.mean(axis=0)
    outer = centre + (quad - centre) * 1.15
    mask_in = np.zeros(gray.shape, np.uint8)
    cv2.fillConvexPoly(mask_in, np.round(quad).astype(np.int32), 1)
    mask_out = np.zeros(gray.shape, np.uint8)
    cv2.fillConvexPoly(mask_out, np.round(outer).astype(np.int32), 1)
    ring = gray[(mask_out > 0) & (mask_in == 0)]
    inside = gray[mask_in > 0]
    if ring.size == 0 or inside.size == 0:
        return False
    return float(np.median(ring)) < float(np.mean(inside))
