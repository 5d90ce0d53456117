"""Parts with and without defects, made here, for the anomaly inspection's tests and bench.

Two families of "parts", each a fixed scene seen again and again by a fixtured camera:

- synthetic parts (:data:`SYNTHETIC_PARTS`), drawn with OpenCV on a textured conveyor: a turned
  ``disc`` (flange with concentric turning marks, bore and four bolt holes), a brushed-metal
  ``bracket`` (L-shaped plate with two holes and a slot) and a printed ``label`` (text, a bar
  code and a logo on a cream card, on cardboard);
- real photographs (:data:`PHOTO_PARTS`): one fixed region of one of scikit-image's sample
  photographs per part -- textures (brick, gravel, grass), objects (coins, the cameraman, the
  coffee cup, the cat's face, the astronaut's face, a motorcycle's engine) and print (a printed
  page, handwriting). The files are read from the installed wheel's ``skimage/data/`` folder
  without importing scikit-image (see photos.py); without the wheel these parts are absent.

A good sample is the part seen once more with the variation of a real cell: shifted by up to
3 px (sub-pixel, both axes), rotated by up to 2 degrees, brightness and contrast each within
5 %, sensor noise (Gaussian, 2 grey levels) and, for the photographs, JPEG compression at a
quality of 75..95.

A defect sample is a fresh good sample (its own jitter) with one defect painted on the part
before the noise and compression (:data:`DEFECTS`, taken in turn):

- ``scratch``: a straight anti-aliased line 1..3 px wide, 10..30 % of the image side long, at
  any angle, 35..70 grey levels brighter or darker than what it crosses;
- ``hole``: a dark ellipse (15..35 % of the light around it, at most grey 45; soft 0.7 px
  edge), 2.5..6 % of the side across;
- ``stain``: a soft-edged blob of rust, oil or water-mark tint, 4..8 % of the side across
  (its visible core is smaller), at 35..60 % opacity;
- ``crack``: a jagged dark polyline 1..2 px wide, 8..20 % of the side long, 6..10 segments
  turning by up to 35 degrees each;
- ``missing``: a piece gone, an irregular polygon 4..7 % of the side across: on the synthetic
  parts a chip out of the part's outline that shows the conveyor; on the photographs a piece
  broken out of the surface, showing the shadowed depth behind it (the region's median colour
  at 25..45 % of its light);
- ``contamination``: a foreign particle 4..7 % of the side across: on the photographs an
  elliptical piece (soft edge) of another photograph pasted in, on the synthetic parts a
  particle of random colour and grain.

Sizes are of modest, realistic defects, not of trivially large ones: at 224x224 a hole is
6..13 px across. The random natural textures (gravel, grass) are the hardest parts by far: a
thin scratch or a small dark hole there looks much like the texture's own gaps and blades, and
a person finds several of them only by comparing with the clean twin.

Every sample depends only on (part, seed, index): asking for more images gives the same first
ones. ``masks`` mark each defect's pixels (its opacity over 25 %; a stain's: the inner half of
its soft outline); ``clean`` holds each defect sample as it was before its defect was painted
(same jitter, noise and compression).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import NamedTuple

import cv2
import numpy as np
from numpy.typing import NDArray
from photos import skimage_data_dir

Image = NDArray[np.uint8]
Float = NDArray[np.float32]

SIZE = 224
"""The default side of every sample, px."""
MARGIN = 16
"""The master scene's margin beyond the sample on each side, px: room for shift and rotation."""

DEFECTS = ("scratch", "hole", "stain", "crack", "missing", "contamination")
SYNTHETIC_PARTS = ("disc", "bracket", "label")

MAX_SHIFT_PX = 3.0
MAX_ROTATION_DEG = 2.0
MAX_PHOTOMETRIC = 0.05
NOISE_GREY = 2.0
JPEG_QUALITY = (75, 95)


@dataclass(frozen=True)
class PhotoPart:
    """One region of one of scikit-image's photographs used as a part."""

    name: str
    file: str
    box: tuple[int, int, int, int]
    """x, y, width, height in the photograph, px (resampled to the sample's size)."""
    kind: str
    """texture | object | print"""


PHOTO_PARTS: tuple[PhotoPart, ...] = (
    PhotoPart("brick", "brick.png", (128, 128, 256, 256), "texture"),
    PhotoPart("gravel", "gravel.png", (128, 128, 256, 256), "texture"),
    PhotoPart("grass", "grass.png", (128, 128, 256, 256), "texture"),
    PhotoPart("coins", "coins.png", (40, 0, 300, 300), "object"),
    PhotoPart("camera", "camera.png", (140, 40, 280, 280), "object"),
    PhotoPart("coffee", "coffee.png", (60, 20, 380, 380), "object"),
    PhotoPart("chelsea", "chelsea.png", (110, 0, 290, 290), "object"),
    PhotoPart("astronaut", "astronaut.png", (100, 10, 300, 300), "object"),
    PhotoPart("motorcycle", "motorcycle_left.png", (250, 200, 280, 280), "object"),
    PhotoPart("page", "page.png", (0, 0, 191, 191), "print"),
    PhotoPart("text", "text.png", (100, 0, 172, 172), "print"),
)

DONORS = ("coffee.png", "gravel.png", "hubble_deep_field.jpg", "rocket.jpg", "chelsea.png")
"""Photographs that contamination is cut from (never the part's own)."""

ALL_PARTS = SYNTHETIC_PARTS + tuple(p.name for p in PHOTO_PARTS)


class Samples(NamedTuple):
    """One part's samples: good images, defect images, each defect's mask (bool, HxW) and
    kind (one of :data:`DEFECTS`), and each defect sample's twin without it. Images are uint8
    BGR (H, W, 3) or grey (H, W)."""

    good: list[Image]
    defects: list[Image]
    masks: list[NDArray[np.bool_]]
    kinds: list[str]
    clean: list[Image]
    """Each defect sample without its defect: the same jitter, noise and compression."""


@dataclass(frozen=True)
class _Scene:
    """A part's master scene, (size + 2 * MARGIN) square, float32 0..255, (H, W, C)."""

    image: Float
    background: Float
    """What is there where the part is not (the synthetic parts' conveyor; for photographs
    the region's median colour, flat)."""
    part: NDArray[np.float32]
    """Where the part is, 0..1 (H, W)."""
    grey: bool
    jpeg: bool


# --- the scenes -------------------------------------------------------------------------------


def _smooth_noise(rng: np.random.Generator, shape: tuple[int, int], sigma: float) -> Float:
    """Gaussian-smoothed white noise scaled to unit standard deviation."""
    field = cv2.GaussianBlur(rng.normal(0, 1, shape).astype(np.float32), (0, 0), sigma)
    return np.asarray(field / max(float(field.std()), 1e-6), np.float32)


def _conveyor(rng: np.random.Generator, side: int, colour: tuple[float, float, float]) -> Float:
    """A textured, unevenly lit belt: low-frequency blotches and fine grain around ``colour``."""
    blotch = _smooth_noise(rng, (side, side), side / 10) * 10
    grain = _smooth_noise(rng, (side, side), 0.8) * 4
    light = np.linspace(-8, 8, side, dtype=np.float32)[None, :]
    shade = (blotch + grain + light)[:, :, None]
    return np.asarray(np.array(colour, np.float32)[None, None, :] + shade, np.float32)


def _disc(rng: np.random.Generator, side: int) -> tuple[Float, Float]:
    c = side / 2
    ys, xs = np.mgrid[0:side, 0:side].astype(np.float32)
    r = np.hypot(xs - c, ys - c)
    radius = 0.36 * side
    turning = 5 * np.sin(2 * np.pi * r / 3.1) + 3 * np.sin(2 * np.pi * r / 11.0)
    light = 25 * ((c - xs) + (c - ys)) / side  # lit from the top left
    metal = 165 + turning + light + _smooth_noise(rng, (side, side), 1.0) * 3
    metal = np.where(np.abs(r - radius + 3) < 2.0, metal + 35, metal)  # chamfer catches light
    mask = np.zeros((side, side), np.uint8)
    cv2.circle(mask, (int(c * 16), int(c * 16)), int(radius * 16), 255, -1, cv2.LINE_AA, 4)
    holes = np.zeros((side, side), np.uint8)
    cv2.circle(holes, (int(c * 16), int(c * 16)), int(0.09 * side * 16), 255, -1, cv2.LINE_AA, 4)
    for k in range(4):
        a = math.pi / 4 + k * math.pi / 2
        u, v = c + 0.24 * side * math.cos(a), c + 0.24 * side * math.sin(a)
        centre = (int(u * 16), int(v * 16))
        cv2.circle(holes, centre, int(0.035 * side * 16), 255, -1, cv2.LINE_AA, 4)
    inside = mask.astype(np.float32) / 255
    hole = holes.astype(np.float32) / 255
    grey = metal * (1 - hole) + 35 * hole
    part = np.repeat(grey[:, :, None], 3, axis=2)
    return np.asarray(part, np.float32), np.asarray(inside * (1 - hole), np.float32)


def _bracket(rng: np.random.Generator, side: int) -> tuple[Float, Float]:
    s = side
    outline = np.array(
        [[0.18, 0.2], [0.82, 0.2], [0.82, 0.42], [0.45, 0.42], [0.45, 0.82], [0.18, 0.82]]
    )
    mask = np.zeros((s, s), np.uint8)
    cv2.fillPoly(mask, [np.int32(outline * s * 16)], 255, cv2.LINE_AA, 4)
    cut = np.zeros((s, s), np.uint8)
    for u, v in ((0.31, 0.31), (0.31, 0.7)):
        cv2.circle(cut, (int(u * s * 16), int(v * s * 16)), int(0.045 * s * 16), 255, -1, 16, 4)
    cv2.rectangle(cut, (int(0.56 * s), int(0.28 * s)), (int(0.74 * s), int(0.34 * s)), 255, -1)
    brushed = cv2.GaussianBlur(
        rng.normal(0, 1, (s, s)).astype(np.float32), (0, 0), sigmaX=9.0, sigmaY=0.5
    )
    brushed = brushed / max(float(brushed.std()), 1e-6) * 8
    metal = 150 + brushed + 15 * np.linspace(-1, 1, s, dtype=np.float32)[:, None]
    part = np.repeat(metal[:, :, None], 3, axis=2) + np.array([4, 2, 0], np.float32)
    inside = (mask.astype(np.float32) / 255) * (1 - cut.astype(np.float32) / 255)
    return np.asarray(part, np.float32), np.asarray(inside, np.float32)


def _label(rng: np.random.Generator, side: int) -> tuple[Float, Float]:
    s = side
    card = np.zeros((s, s, 3), np.float32)
    card[:] = (205, 222, 232)  # cream, BGR
    card += _smooth_noise(rng, (s, s), 1.2)[:, :, None] * 2.5
    ink = np.zeros((s, s), np.uint8)
    cv2.putText(ink, "LOT 4711-B", (int(0.2 * s), int(0.3 * s)), 0, s / 420, 255, 2, 16)
    cv2.putText(ink, "cellvision 24V", (int(0.2 * s), int(0.42 * s)), 0, s / 560, 255, 1, 16)
    x = int(0.2 * s)
    bars = rng.integers(1, 4, 40)
    for k, width in enumerate(bars):
        if x + width > 0.8 * s:
            break
        if k % 2 == 0:
            cv2.rectangle(ink, (x, int(0.52 * s)), (x + int(width) - 1, int(0.72 * s)), 255, -1)
        x += int(width)
    inked = ink.astype(np.float32)[:, :, None] / 255
    card = card * (1 - inked) + 25 * inked
    cv2.rectangle(
        card, (int(0.62 * s), int(0.2 * s)), (int(0.78 * s), int(0.32 * s)), (40, 40, 190), -1
    )
    mask = np.zeros((s, s), np.uint8)
    cv2.rectangle(mask, (int(0.15 * s), int(0.15 * s)), (int(0.85 * s), int(0.78 * s)), 255, -1)
    return np.asarray(card, np.float32), mask.astype(np.float32) / 255


_DRAW = {"disc": _disc, "bracket": _bracket, "label": _label}
_BELT = {"disc": (70, 72, 76), "bracket": (45, 48, 52), "label": (70, 110, 150)}


def _synthetic_scene(name: str, side: int) -> _Scene:
    rng = np.random.default_rng([ALL_PARTS.index(name), 7])
    belt = _conveyor(rng, side, _BELT[name])
    part, inside = _DRAW[name](rng, side)
    alpha = inside[:, :, None]
    image = part * alpha + belt * (1 - alpha)
    return _Scene(np.asarray(image, np.float32), belt, inside, grey=False, jpeg=False)


def _read(name: str) -> NDArray[np.uint8] | None:
    folder = skimage_data_dir()
    if folder is None or not (folder / name).is_file():
        return None
    image = cv2.imread(str(folder / name), cv2.IMREAD_UNCHANGED)
    if image is None:
        return None
    if image.ndim == 3 and image.shape[2] == 4:
        image = cv2.cvtColor(image, cv2.COLOR_BGRA2BGR)
    return np.asarray(image, np.uint8)


def _photo_scene(part: PhotoPart, side: int) -> _Scene | None:
    photo = _read(part.file)
    if photo is None:
        return None
    x, y, w, h = part.box
    crop = photo[y : y + h, x : x + w]
    resized = cv2.resize(crop, (side, side), interpolation=cv2.INTER_AREA)
    image = resized.astype(np.float32)
    grey = image.ndim == 2
    if grey:
        image = image[:, :, None]
    flat = np.median(image.reshape(-1, image.shape[2]), axis=0).astype(np.float32)
    background = np.broadcast_to(flat, image.shape).astype(np.float32)
    inside = np.ones((side, side), np.float32)
    return _Scene(image, background, inside, grey=grey, jpeg=True)


def photo_available() -> bool:
    """Whether scikit-image's photographs can be read here (else only synthetic parts)."""
    return skimage_data_dir() is not None


def available_parts() -> tuple[str, ...]:
    """The parts that can be made here: the synthetic ones, and the photographs' if found."""
    return ALL_PARTS if photo_available() else SYNTHETIC_PARTS


# --- one sample --------------------------------------------------------------------------------


def _jitter(scene: _Scene, rng: np.random.Generator, size: int) -> tuple[Float, Float, Float]:
    """The scene moved, turned, cropped to ``size`` and relit: (image, background, part)."""
    side = scene.image.shape[0]
    angle = rng.uniform(-MAX_ROTATION_DEG, MAX_ROTATION_DEG)
    du, dv = rng.uniform(-MAX_SHIFT_PX, MAX_SHIFT_PX, 2)
    matrix = cv2.getRotationMatrix2D((side / 2 - 0.5, side / 2 - 0.5), float(angle), 1.0)
    matrix[:, 2] += (du - (side - size) / 2, dv - (side - size) / 2)

    def warp(plane: Float) -> Float:
        out = cv2.warpAffine(
            plane, matrix, (size, size), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT
        )
        return np.asarray(out if out.ndim == plane.ndim else out[:, :, None], np.float32)

    image = warp(scene.image)
    background = warp(np.ascontiguousarray(scene.background))
    part = np.asarray(
        cv2.warpAffine(scene.part, matrix, (size, size), flags=cv2.INTER_LINEAR), np.float32
    )
    contrast = rng.uniform(1 - MAX_PHOTOMETRIC, 1 + MAX_PHOTOMETRIC)
    brightness = rng.uniform(1 - MAX_PHOTOMETRIC, 1 + MAX_PHOTOMETRIC)
    mean = float(image.mean())
    image = (image - mean) * contrast + mean * brightness
    background = (background - mean) * contrast + mean * brightness
    return image, background, part


def _finish(image: Float, scene: _Scene, rng: np.random.Generator) -> Image:
    """Sensor noise, rounding and (photographs) JPEG: the camera's uint8 image."""
    noisy = image + rng.normal(0, NOISE_GREY, image.shape).astype(np.float32)
    out = np.asarray(np.clip(np.rint(noisy), 0, 255), np.uint8)
    if scene.grey:
        out = out[:, :, 0]
    if scene.jpeg:
        quality = int(rng.integers(JPEG_QUALITY[0], JPEG_QUALITY[1] + 1))
        ok, data = cv2.imencode(".jpg", out, [cv2.IMWRITE_JPEG_QUALITY, quality])
        if ok:
            decoded = cv2.imdecode(data, cv2.IMREAD_UNCHANGED)
            out = np.asarray(decoded, np.uint8)
    return np.ascontiguousarray(out)


# --- defects -----------------------------------------------------------------------------------


def _where(part: Float, rng: np.random.Generator, size: int, margin: float) -> tuple[float, float]:
    """A random point on the part, at least ``margin`` px inside it and the image."""
    eroded = cv2.erode((part > 0.5).astype(np.uint8), np.ones((3, 3), np.uint8), iterations=4)
    border = int(max(margin, 0.12 * size))
    eroded[:border] = 0
    eroded[-border:] = 0
    eroded[:, :border] = 0
    eroded[:, -border:] = 0
    vs, us = np.nonzero(eroded)
    if us.size == 0:
        return size / 2, size / 2
    k = int(rng.integers(us.size))
    return float(us[k]) + rng.uniform(-0.5, 0.5), float(vs[k]) + rng.uniform(-0.5, 0.5)


def _sub(points: NDArray[np.float64]) -> NDArray[np.int32]:
    """Points for OpenCV's drawing at 4 fractional bits."""
    return np.asarray(np.rint(points * 16), np.int32)


def _alpha(canvas: NDArray[np.uint8], soften: float = 0.0) -> Float:
    alpha = canvas.astype(np.float32) / 255
    if soften > 0:
        alpha = cv2.GaussianBlur(alpha, (0, 0), soften)
    return np.asarray(alpha, np.float32)


def _blend(image: Float, alpha: Float, target: Float) -> Float:
    a = alpha[:, :, None]
    return np.asarray(image * (1 - a) + target * a, np.float32)


def _polygon(rng: np.random.Generator, centre: tuple[float, float], across: float) -> NDArray:
    """An irregular closed polygon ``across`` px wide (about) around ``centre``."""
    n = int(rng.integers(5, 9))
    step = 2 * np.pi / n  # evenly round with jitter: never a sliver
    angles = np.arange(n) * step + rng.uniform(-0.3, 0.3, n) * step + rng.uniform(0, step)
    radii = across / 2 * rng.uniform(0.6, 1.0, n)
    return np.stack(
        [centre[0] + radii * np.cos(angles), centre[1] + radii * np.sin(angles)], axis=1
    )


def _donor(rng: np.random.Generator, avoid: str, across: int) -> Float | None:
    names = [n for n in DONORS if n != avoid]
    photo = _read(names[int(rng.integers(len(names)))])
    if photo is None:
        return None
    h, w = photo.shape[:2]
    y, x = int(rng.integers(0, h - across)), int(rng.integers(0, w - across))
    piece = photo[y : y + across, x : x + across].astype(np.float32)
    return piece if piece.ndim == 3 else np.repeat(piece[:, :, None], 3, axis=2)


def _defect(
    kind: str,
    image: Float,
    background: Float,
    part: Float,
    rng: np.random.Generator,
    *,
    synthetic: bool,
    own_file: str,
) -> tuple[Float, NDArray[np.bool_]]:
    size = image.shape[0]
    canvas = np.zeros((size, size), np.uint8)
    shape: Float | None = None
    channels = image.shape[2]
    if kind == "scratch":
        length = rng.uniform(0.10, 0.30) * size
        u, v = _where(part, rng, size, length / 2)
        theta = rng.uniform(0, np.pi)
        d = np.array([math.cos(theta), math.sin(theta)]) * length / 2
        a, b = _sub(np.array([u, v]) - d), _sub(np.array([u, v]) + d)
        width = int(rng.integers(1, 4))
        cv2.line(canvas, tuple(int(t) for t in a), tuple(int(t) for t in b), 255, width, 16, 4)
        alpha = _alpha(canvas)
        delta = rng.uniform(35, 70) * (1 if rng.random() < 0.65 else -1)
        out = _blend(image, alpha, image + delta)
    elif kind == "hole":
        across = rng.uniform(0.025, 0.06) * size
        u, v = _where(part, rng, size, across)
        axes = (across / 2, across / 2 * rng.uniform(0.6, 1.0))
        centre = tuple(int(t) for t in _sub(np.array([u, v])))
        sub_axes = tuple(int(t) for t in _sub(np.array(axes)))
        angle = float(rng.uniform(0, 180))
        cv2.ellipse(canvas, centre, sub_axes, angle, 0, 360, 255, -1, 16, 4)
        alpha = _alpha(canvas, 0.7)
        depth = np.minimum(image * rng.uniform(0.15, 0.35), 45.0)
        out = _blend(image, alpha, np.asarray(depth, np.float32))
    elif kind == "stain":
        across = rng.uniform(0.04, 0.08) * size
        u, v = _where(part, rng, size, across)
        cv2.fillPoly(canvas, [_sub(_polygon(rng, (u, v), across))], 255, 16, 4)
        shape = _alpha(canvas, across / 6)  # the mask: inside its soft outline's half
        alpha = shape * rng.uniform(0.35, 0.6)
        tints = ((40, 70, 120), (30, 32, 35), (200, 200, 190))  # rust, oil, water mark (BGR)
        tint = np.array(tints[int(rng.integers(len(tints)))], np.float32)[:channels]
        if channels == 1:
            tint = np.array([np.mean(tints[int(rng.integers(len(tints)))])], np.float32)
        out = _blend(image, alpha, np.broadcast_to(tint, image.shape).astype(np.float32))
    elif kind == "crack":
        length = rng.uniform(0.08, 0.20) * size
        u, v = _where(part, rng, size, length / 2)
        n = int(rng.integers(6, 11))
        theta = rng.uniform(0, 2 * np.pi)
        points = [np.array([u, v])]
        for _ in range(n):
            theta += rng.uniform(-0.6, 0.6)
            points.append(points[-1] + length / n * np.array([math.cos(theta), math.sin(theta)]))
        line = np.stack(points) - (points[-1] - points[0]) / 2  # centred on the point
        width = int(rng.integers(1, 3))
        cv2.polylines(canvas, [_sub(line)], False, 255, width, 16, 4)
        alpha = _alpha(canvas)
        out = _blend(image, alpha, image * rng.uniform(0.25, 0.5))
    elif kind == "missing":
        across = rng.uniform(0.04, 0.07) * size
        if synthetic:  # a chip out of the outline: the conveyor shows through
            edge = cv2.morphologyEx(
                (part > 0.5).astype(np.uint8), cv2.MORPH_GRADIENT, np.ones((3, 3), np.uint8)
            )
            border = int(0.12 * size)
            edge[:border] = 0
            edge[-border:] = 0
            edge[:, :border] = 0
            edge[:, -border:] = 0
            vs, us = np.nonzero(edge)
            k = int(rng.integers(us.size))
            u, v = float(us[k]), float(vs[k])
        else:
            u, v = _where(part, rng, size, across)
        cv2.fillPoly(canvas, [_sub(_polygon(rng, (u, v), across))], 255, 16, 4)
        alpha = _alpha(canvas, 0.5)
        if synthetic:
            alpha = alpha * np.clip(part, 0, 1)  # only the part loses material
            behind = background
        else:  # broken out: the shadowed depth behind the surface
            behind = background * np.float32(rng.uniform(0.25, 0.45))
        out = _blend(image, alpha, behind)
    elif kind == "contamination":
        across = rng.uniform(0.04, 0.07) * size
        u, v = _where(part, rng, size, across)
        side = int(math.ceil(across)) + 2
        piece = None if synthetic else _donor(rng, own_file, side)
        if piece is None:  # a particle of random colour and grain
            colour = rng.uniform(20, 235, 3).astype(np.float32)
            grain = rng.normal(0, 12, (side, side)).astype(np.float32)[:, :, None]
            piece = colour[None, None, :] + grain
        if channels == 1:
            piece = piece.mean(axis=2, keepdims=True)
        target = image.copy()
        x0, y0 = int(round(u)) - side // 2, int(round(v)) - side // 2
        target[y0 : y0 + side, x0 : x0 + side] = piece
        cv2.fillPoly(canvas, [_sub(_polygon(rng, (u, v), across))], 255, 16, 4)
        alpha = _alpha(canvas, 0.6) * 0.95
        out = _blend(image, alpha, target)
    else:
        raise ValueError(f"unknown defect kind {kind!r}: one of {DEFECTS}")
    return out, (shape > 0.5) if shape is not None else (alpha > 0.25)


# --- the samples -------------------------------------------------------------------------------


def _scene(name: str, size: int) -> tuple[_Scene, str] | None:
    side = size + 2 * MARGIN
    if name in SYNTHETIC_PARTS:
        return _synthetic_scene(name, side), ""
    for part in PHOTO_PARTS:
        if part.name == name:
            scene = _photo_scene(part, side)
            return None if scene is None else (scene, part.file)
    raise ValueError(f"unknown part {name!r}: one of {ALL_PARTS}")


def part_samples(
    name: str,
    seed: int = 0,
    *,
    size: int = SIZE,
    good: int = 20,
    defects: int = 12,
    kinds: Sequence[str] = DEFECTS,
    first_good: int = 0,
) -> Samples | None:
    """``good`` good samples (from index ``first_good`` on) and ``defects`` defect samples
    (kinds from ``kinds`` in turn) of part ``name`` (:data:`ALL_PARTS`), ``size`` px square;
    None for a photograph's part where scikit-image's files are not installed. Deterministic
    in (name, seed, index): training images 0..n-1 and held-out ones from ``first_good`` =
    1000 on never overlap."""
    made = _scene(name, size)
    if made is None:
        return None
    scene, own_file = made
    index = ALL_PARTS.index(name)
    goods: list[Image] = []
    for k in range(first_good, first_good + good):
        rng = np.random.default_rng([seed, index, 0, k])
        image, _, _ = _jitter(scene, rng, size)
        goods.append(_finish(image, scene, rng))
    bad: list[Image] = []
    masks: list[NDArray[np.bool_]] = []
    made_kinds: list[str] = []
    clean: list[Image] = []
    for k in range(defects):
        rng = np.random.default_rng([seed, index, 1, k])
        kind = kinds[k % len(kinds)]
        image, background, part = _jitter(scene, rng, size)
        painted, mask = _defect(
            kind,
            image,
            background,
            part,
            rng,
            synthetic=name in SYNTHETIC_PARTS,
            own_file=own_file,
        )
        # the same noise and compression for both twins
        bad.append(_finish(painted, scene, np.random.default_rng([seed, index, 2, k])))
        clean.append(_finish(image, scene, np.random.default_rng([seed, index, 2, k])))
        masks.append(mask)
        made_kinds.append(kind)
    return Samples(goods, bad, masks, made_kinds, clean)


def synthetic_part(
    name: str = "disc", seed: int = 0, *, size: int = SIZE, good: int = 20, defects: int = 12
) -> tuple[list[Image], list[Image], list[NDArray[np.bool_]]]:
    """(good images, defect images, defect masks) of a synthetic part: see :func:`part_samples`."""
    if name not in SYNTHETIC_PARTS:
        raise ValueError(f"unknown synthetic part {name!r}: one of {SYNTHETIC_PARTS}")
    samples = part_samples(name, seed, size=size, good=good, defects=defects)
    assert samples is not None  # synthetic parts need no files
    return samples.good, samples.defects, samples.masks


# --- the measure -------------------------------------------------------------------------------


def auroc(good_scores: Sequence[float], defect_scores: Sequence[float]) -> float:
    """Image AUROC: the probability that a defect image scores above a good one (ties count
    half), from ranks (Mann-Whitney U / (n_good * n_defect)). 1.0: every defect above every
    good image; 0.5: no better than chance."""
    good = np.asarray(good_scores, np.float64).ravel()
    bad = np.asarray(defect_scores, np.float64).ravel()
    if good.size == 0 or bad.size == 0:
        raise ValueError("AUROC needs at least one good and one defect score")
    if not (np.isfinite(good).all() and np.isfinite(bad).all()):
        raise ValueError("AUROC needs finite scores")
    both = np.concatenate([good, bad])
    order = np.argsort(both, kind="mergesort")
    ordered = both[order]
    ranks = np.empty(both.size, np.float64)
    start = 0
    while start < both.size:  # tied runs share their average rank (1-based)
        end = start
        while end + 1 < both.size and ordered[end + 1] == ordered[start]:
            end += 1
        ranks[order[start : end + 1]] = (start + end) / 2 + 1
        start = end + 1
    u = ranks[good.size :].sum() - bad.size * (bad.size + 1) / 2
    return float(u / (good.size * bad.size))
