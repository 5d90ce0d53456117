"""Synthetic parts for the anomaly tests: a drawn part (a machined plate with holes, print and a
fixed surface texture) placed with a small jitter (sub-pixel shift, a fraction of a degree,
brightness, sensor noise), and defects drawn on it with their masks: scratches, holes and
stains. Everything is drawn from a seeded ``numpy.random.Generator``: the same seed gives the
same bytes.

Two layouts:

- :func:`good_part` / :func:`defective_part`: a ``SIZE`` x ``SIZE`` image filled by the part
  (what an ROI of a fixtured part would see);
- :func:`placed_plate`: a 320 x 240 camera image with a plate (a big and a small hole that a
  job's locate and fixture steps find) moved and turned anywhere on it, optionally with a
  defect in the plate's middle, for the job step.
"""

from __future__ import annotations

import math
from typing import Literal

import cv2
import numpy as np
from numpy.typing import NDArray

Defect = Literal["scratch", "hole", "stain"]
DEFECTS: tuple[Defect, ...] = ("scratch", "hole", "stain")
SIZE = 224
"""Side of :func:`good_part`'s images (px): the backbone's own input size."""

Image = NDArray[np.uint8]
Mask = NDArray[np.bool_]


def _texture(height: int, width: int, seed: int) -> NDArray[np.float32]:
    """A fixed machined-surface texture (grey levels about ±8), the same for every part."""
    rng = np.random.default_rng(seed)
    noise = rng.normal(0.0, 1.0, (height, width)).astype(np.float32)
    grain = cv2.GaussianBlur(noise, (0, 0), sigmaX=6.0, sigmaY=0.8)
    grain *= 8.0 / max(float(grain.std()), 1e-6)
    return np.asarray(grain, np.float32)


def _canonical_part() -> NDArray[np.float32]:
    """The ideal part, float grey levels, ``SIZE`` x ``SIZE``, before any jitter."""
    part = np.full((SIZE, SIZE), 70.0, np.float32)
    cv2.rectangle(part, (14, 14), (SIZE - 15, SIZE - 15), 185.0, -1, cv2.LINE_AA)
    part[14 : SIZE - 14, 14 : SIZE - 14] += _texture(SIZE - 28, SIZE - 28, 7)
    for cx, cy in ((40, 40), (SIZE - 41, 40), (40, SIZE - 41), (SIZE - 41, SIZE - 41)):
        cv2.circle(part, (cx, cy), 9, 45.0, -1, cv2.LINE_AA)
        cv2.circle(part, (cx, cy), 13, 150.0, 2, cv2.LINE_AA)
    cv2.rectangle(part, (70, 96), (154, 128), 120.0, 2, cv2.LINE_AA)
    ink = np.zeros((SIZE, SIZE), np.uint8)  # putText draws on 8 bits only
    cv2.putText(ink, "C31", (82, 122), cv2.FONT_HERSHEY_SIMPLEX, 0.8, 255, 2, cv2.LINE_AA)
    alpha = ink.astype(np.float32) / 255.0
    return np.asarray(part * (1.0 - alpha) + 60.0 * alpha, np.float32)


_PART = _canonical_part()


def _jittered(rng: np.random.Generator, canvas: NDArray[np.float32]) -> NDArray[np.float32]:
    height, width = canvas.shape
    angle = rng.uniform(-0.6, 0.6)
    matrix = cv2.getRotationMatrix2D((width / 2.0, height / 2.0), angle, 1.0)
    matrix[:, 2] += rng.uniform(-1.5, 1.5, 2)
    moved = cv2.warpAffine(
        canvas, matrix, (width, height), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT
    )
    return np.asarray(moved * rng.uniform(0.96, 1.04) + rng.uniform(-4.0, 4.0), np.float32)


def _finish(rng: np.random.Generator, grey: NDArray[np.float32]) -> Image:
    noisy = grey + rng.normal(0.0, 2.0, grey.shape).astype(np.float32)
    bytes_ = np.clip(np.round(noisy), 0, 255).astype(np.uint8)
    return np.ascontiguousarray(cv2.cvtColor(bytes_, cv2.COLOR_GRAY2BGR))


def draw_defect(
    rng: np.random.Generator,
    grey: NDArray[np.float32],
    kind: Defect,
    box: tuple[int, int, int, int],
) -> Mask:
    """Draw a defect of ``kind`` into ``grey`` (in place) somewhere inside ``box`` (x0, y0,
    x1, y1 px); returns the defect's mask (True where it changed the part)."""
    x0, y0, x1, y1 = box
    marks = np.zeros(grey.shape, np.float32)
    cx, cy = int(rng.integers(x0 + 20, x1 - 20)), int(rng.integers(y0 + 20, y1 - 20))
    if kind == "scratch":
        angle = rng.uniform(0.0, math.pi)
        half = rng.uniform(14.0, 20.0)
        dx, dy = half * math.cos(angle), half * math.sin(angle)
        start = (int(round(cx - dx)), int(round(cy - dy)))
        end = (int(round(cx + dx)), int(round(cy + dy)))
        cv2.line(marks, start, end, 1.0, 2, cv2.LINE_AA)
        grey -= marks * 110.0
    elif kind == "hole":
        radius = int(rng.integers(5, 8))
        cv2.circle(marks, (cx, cy), radius, 1.0, -1, cv2.LINE_AA)
        grey[:] = grey * (1.0 - marks) + 35.0 * marks
    else:
        axes = (int(rng.integers(9, 14)), int(rng.integers(6, 10)))
        cv2.ellipse(marks, (cx, cy), axes, rng.uniform(0, 180), 0, 360, 1.0, -1, cv2.LINE_AA)
        marks = cv2.GaussianBlur(marks, (0, 0), 2.5)
        grey -= marks * 70.0
    return np.asarray(marks > 0.05)


def good_part(rng: np.random.Generator) -> Image:
    """A good part, BGR uint8 ``SIZE`` x ``SIZE``, jittered by ``rng``."""
    return _finish(rng, _jittered(rng, _PART))


def defective_part(rng: np.random.Generator, kind: Defect) -> tuple[Image, Mask]:
    """A jittered part with one defect of ``kind`` on its plate, and the defect's mask."""
    grey = _jittered(rng, _PART)
    mask = draw_defect(rng, grey, kind, (24, 24, SIZE - 24, SIZE - 24))
    return _finish(rng, grey), mask


# --- the plate of the job test: a part that moves and turns in a camera image ---------------

PLATE_SIZE = (200, 120)
"""The plate's canvas (width, height) px."""
PLATE_ORIGIN = (30.0, 60.0)
"""The big hole's centre on the canvas: the part frame's origin (x towards the small hole)."""
PLATE_WINDOW = (20, -40, 64, 80)
"""The anomaly step's ROI in the part frame [x, y, width, height] px (between the holes)."""
CAMERA_SIZE = (320, 240)


def _plate_canvas() -> NDArray[np.float32]:
    width, height = PLATE_SIZE
    canvas = np.full((height, width), 200.0, np.float32)
    canvas += _texture(height, width, 11) * 0.6
    ox, oy = int(PLATE_ORIGIN[0]), int(PLATE_ORIGIN[1])
    cv2.circle(canvas, (ox, oy), 12, 40.0, -1, cv2.LINE_AA)
    cv2.circle(canvas, (ox + 100, oy), 9, 40.0, -1, cv2.LINE_AA)
    cv2.rectangle(canvas, (56, 30), (84, 90), 140.0, 2, cv2.LINE_AA)
    cv2.line(canvas, (60, 60), (80, 60), 120.0, 2, cv2.LINE_AA)
    return canvas


_PLATE = _plate_canvas()


def placed_plate(
    rng: np.random.Generator,
    u0: float,
    v0: float,
    angle: float,
    defect: Defect | None = None,
) -> tuple[Image, Mask | None]:
    """A 320x240 grey camera image of the plate with its frame at (u0, v0) px turned by
    ``angle`` rad (plus sensor noise), and, with ``defect``, that defect drawn in the anomaly
    step's window; its mask is in camera pixels."""
    canvas = _PLATE.copy()
    mask = None
    if defect is not None:
        wx, wy, ww, wh = PLATE_WINDOW
        ox, oy = PLATE_ORIGIN
        box = (int(ox + wx) + 4, int(oy + wy) + 4, int(ox + wx + ww) - 4, int(oy + wy + wh) - 4)
        canvas_mask = draw_defect(rng, canvas, defect, box)
    c, s = math.cos(angle), math.sin(angle)
    ox, oy = PLATE_ORIGIN
    matrix = np.array([[c, -s, u0 - c * ox + s * oy], [s, c, v0 - s * ox - c * oy]])
    placed = cv2.warpAffine(canvas, matrix, CAMERA_SIZE, flags=cv2.INTER_LINEAR, borderValue=40.0)
    if defect is not None:
        mask = cv2.warpAffine(canvas_mask.astype(np.uint8) * 255, matrix, CAMERA_SIZE, flags=0) > 0
    noisy = placed + rng.normal(0.0, 2.0, placed.shape).astype(np.float32)
    return np.clip(np.round(noisy), 0, 255).astype(np.uint8), mask


def dilate(mask: Mask, pixels: int) -> Mask:
    """``mask`` grown by ``pixels`` in every direction."""
    kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * pixels + 1, 2 * pixels + 1))
    return np.asarray(cv2.dilate(mask.astype(np.uint8), kernel) > 0)


def auroc(good: list[float], bad: list[float]) -> float:
    """The area under the ROC curve of scores where higher means defective (ties count 1/2)."""
    wins = sum((b > g) + 0.5 * (b == g) for b in bad for g in good)
    return float(wins) / (len(good) * len(bad))


__all__ = [
    "CAMERA_SIZE",
    "DEFECTS",
    "PLATE_ORIGIN",
    "PLATE_WINDOW",
    "SIZE",
    "Defect",
    "auroc",
    "defective_part",
    "dilate",
    "draw_defect",
    "good_part",
    "placed_plate",
]
