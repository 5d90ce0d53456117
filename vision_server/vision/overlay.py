"""Result overlay like the paper's Figure 4b: ROI in green, detections in red, the verdict."""

from __future__ import annotations

from collections.abc import Sequence

import cv2
import numpy as np
from numpy.typing import ArrayLike, NDArray

from vision_server.vision._checks import check_image, check_roi
from vision_server.vision.locate import Feature

__all__ = ["draw_overlay"]

GREEN = (0, 200, 0)
RED = (0, 0, 255)


def _pt(u: float, v: float) -> tuple[int, int]:
    # 4 fractional bits: sub-pixel drawing with cv2's ``shift``.
    return (round(u * 16), round(v * 16))


def draw_overlay(
    image: NDArray[np.uint8],
    *,
    roi: Sequence[float] | None = None,
    features: Sequence[Feature] = (),
    quads: Sequence[ArrayLike] = (),
    verdict: str | None = None,
    passed: bool | None = None,
) -> NDArray[np.uint8]:
    """A BGR copy of ``image`` with the ROI (green), detections (red) and the verdict text.

    Parameters
    ----------
    roi : [u, v, width, height], optional
        Drawn as a green rectangle.
    features : sequence of Feature
        Drawn in red: circles with their radius, other features as a cross with a short line
        along their angle.
    quads : sequence of (4, 2) array_like
        E.g. QR corners c0..c3, drawn in red with c0 marked.
    verdict : str, optional
        Text at the top-left, green if ``passed``, red if not, white if ``passed`` is None.
    """
    img = check_image(image)
    out = cv2.cvtColor(img, cv2.COLOR_GRAY2BGR) if img.ndim == 2 else img.copy()
    scale = max(1, round(max(out.shape[:2]) / 640))
    if roi is not None:
        u, v, w, h = check_roi(roi, out.shape)
        cv2.rectangle(out, (u, v), (u + w - 1, v + h - 1), GREEN, scale)
    for f in features:
        centre = _pt(f.u, f.v)
        if f.radius is not None:
            cv2.circle(out, centre, round(f.radius * 16), RED, scale, cv2.LINE_AA, 4)
        size = 8.0 * scale
        cv2.line(out, _pt(f.u - size, f.v), _pt(f.u + size, f.v), RED, scale, cv2.LINE_AA, 4)
        cv2.line(out, _pt(f.u, f.v - size), _pt(f.u, f.v + size), RED, scale, cv2.LINE_AA, 4)
        if f.angle:
            end = (f.u + 2 * size * np.cos(f.angle), f.v - 2 * size * np.sin(f.angle))
            cv2.line(out, centre, _pt(*end), RED, scale, cv2.LINE_AA, 4)
    for quad in quads:
        q = np.asarray(quad, dtype=np.float64).reshape(4, 2)
        pts = np.round(q * 16).astype(np.int32).reshape(-1, 1, 2)
        cv2.polylines(out, [pts], True, RED, scale, cv2.LINE_AA, 4)
        cv2.circle(out, _pt(*q[0]), 4 * scale * 16, RED, -1, cv2.LINE_AA, 4)
    if verdict:
        colour = (255, 255, 255) if passed is None else (GREEN if passed else RED)
        font = cv2.FONT_HERSHEY_SIMPLEX
        (tw, th), base = cv2.getTextSize(verdict, font, 0.8 * scale, 2 * scale)
        cv2.rectangle(out, (0, 0), (tw + 12 * scale, th + base + 12 * scale), (0, 0, 0), -1)
        cv2.putText(
            out,
            verdict,
            (6 * scale, th + 6 * scale),
            font,
            0.8 * scale,
            colour,
            2 * scale,
            cv2.LINE_AA,
        )
    return np.asarray(out, dtype=np.uint8)
