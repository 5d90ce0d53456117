"""QR code reading: several decoders, preprocessing where they miss, corners in printed order.

:func:`read_qr` returns :class:`QRCode` objects whose ``corners`` follow docs/conventions.md:
``c0`` top-left, ``c1`` top-right, ``c2`` bottom-right (the corner without a finder pattern),
``c3`` bottom-left of the code as printed, in full-image pixels ``(u, v)`` with sub-pixel
precision (the outer boundary of the dark modules, without the quiet zone).

Decoders, in order: zxing-cpp (the fastest and the best single decoder on real photographs),
pyzbar (zbar, the paper's choice), OpenCV's ``QRCodeDetector`` and ``QRCodeDetectorAruco``.
Each runs on the plain grey image only when the ones before it found nothing (or nothing
matching ``expect``): the common case costs one zxing-cpp call, and the slower decoders are
kept for the images zxing-cpp misses (issue 19). Only then are preprocessed copies tried:
upscaling of small images, downscaling of large ones, smoothing, sharpening, adaptive
threshold, inversion and a 45° rotation. The same code found several times is reported once.

Corner order. zxing-cpp reports the corners in symbol order, and its order is used as it is
(put clockwise on the screen). The other decoders report them in their own order and starting
point, so for them the order is recomputed from the image: the quadrilateral is put in
clockwise order on the screen, the image is rectified and the corner whose diagonal does not
show the 1:1:3:1:1 profile of a finder pattern is ``c2``; ``c0`` is the opposite corner. A
code on a board seen from the front is clockwise on the screen. A *mirrored* image (a code seen
in a mirror, or a flipped sensor) reverses the winding; we do not detect mirroring: ``c0`` is
still the corner of the top-left finder pattern and ``c2`` the corner without one, and the
order stays clockwise on the screen, so ``c1`` and ``c3`` are then the printed bottom-left and
top-right corners (the corners of a real code that would produce that image seen from the
front).

Sub-pixel corners. Along each of the four sides, grey-level profiles across the side are
sampled (bilinear) and the first crossing of the mid-level between the quiet zone and the dark
modules, coming from outside, is located to a fraction of a pixel. Where the outermost module
is light the crossing lies a module or more inside; those points are removed by a one-sided
robust line fit (they can only lie inwards). The corners are the intersections of the four
lines (straight lines: for a lens with distortion they are the best straight lines through a
slightly curved side).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from functools import lru_cache

import cv2
import numpy as np
import zxingcpp
from numpy.typing import NDArray
from pyzbar import pyzbar

from .errors import BadImageError, NotFoundError, RoiError
from .expect import Expect, describe, matches

__all__ = ["QRCode", "read_qr", "decode_raw", "order_corners", "refine_corners"]

FloatArray = NDArray[np.float64]
GrayImage = NDArray[np.uint8]

_NEXT = [1, 2, 3, 0]  # the corner after each one (side k runs from corner k to _NEXT[k])
_PREV = [3, 0, 1, 2]


@dataclass(frozen=True)
class QRCode:
    """A decoded QR code: ``text``; ``corners`` (4, 2) float64 full-image pixels ``(u, v)`` in
    the order c0 top-left, c1 top-right, c2 bottom-right, c3 bottom-left (as printed);
    ``decoder`` names the decoder and the preprocessing that found it (e.g. ``"zxing+up2"``);
    ``modules``: the symbol's modules across (17 + 4 version) when the decoder reports its
    version, else None."""

    text: str
    corners: FloatArray
    decoder: str
    modules: int | None = None


@dataclass
class _Raw:
    text: str
    quad: FloatArray  # (4, 2) full-image pixels, any order
    decoder: str
    version: int | None = None
    hits: int = 1


# --- decoders ------------------------------------------------------------------------------


def _bytes_text(data: bytes) -> str:
    try:
        return data.decode("utf-8")
    except UnicodeDecodeError:
        return data.decode("latin-1")


def _pyzbar(gray: GrayImage) -> list[_Raw]:
    out = []
    for d in pyzbar.decode(gray, symbols=[pyzbar.ZBarSymbol.QRCODE]):
        if len(d.polygon) != 4:
            continue
        quad = np.array([[p.x, p.y] for p in d.polygon], dtype=np.float64)
        out.append(_Raw(_bytes_text(d.data), quad, "pyzbar"))
    return out


def _zxing(gray: GrayImage) -> list[_Raw]:
    out = []
    for b in zxingcpp.read_barcodes(
        gray,
        formats=zxingcpp.BarcodeFormats(zxingcpp.BarcodeFormat.QRCode),
        text_mode=zxingcpp.TextMode.Plain,  # the payload as is (HRI spells out <SOH> etc.)
    ):
        if not b.valid:
            continue
        pos = b.position
        quad = np.array(
            [
                [pos.top_left.x, pos.top_left.y],
                [pos.top_right.x, pos.top_right.y],
                [pos.bottom_right.x, pos.bottom_right.y],
                [pos.bottom_left.x, pos.bottom_left.y],
            ],
            dtype=np.float64,
        )
        version: int | None = None
        try:
            extra = b.extra
            version = int(extra.get("Version", "")) if isinstance(extra, dict) else None
        except (AttributeError, TypeError, ValueError):
            version = None
        out.append(_Raw(b.text, quad, "zxing", version))
    return out


def _opencv_with(
    detector: cv2.QRCodeDetector | cv2.QRCodeDetectorAruco, name: str
) -> Callable[[GrayImage], list[_Raw]]:
    def run(gray: GrayImage) -> list[_Raw]:
        try:
            ok, payloads, points, _ = detector.detectAndDecodeBytesMulti(gray)
        except cv2.error:
            return []
        if not ok or points is None:
            return []
        out = []
        for data, pts in zip(payloads, np.asarray(points, dtype=np.float64), strict=False):
            if data:
                out.append(_Raw(_bytes_text(bytes(data)), pts.reshape(4, 2), name))
        return out

    return run


def _opencv(gray: GrayImage) -> list[_Raw]:
    return _opencv_with(cv2.QRCodeDetector(), "opencv")(gray)


def _opencv_aruco(gray: GrayImage) -> list[_Raw]:
    return _opencv_with(cv2.QRCodeDetectorAruco(), "opencv_aruco")(gray)


DECODERS: dict[str, Callable[[GrayImage], list[_Raw]]] = {
    "pyzbar": _pyzbar,
    "zxing": _zxing,
    "opencv": _opencv,
    "opencv_aruco": _opencv_aruco,
}


# --- preprocessing -------------------------------------------------------------------------
# Each variant returns the processed image and a map from its pixels back to the input's.

Variant = tuple[GrayImage, Callable[[FloatArray], FloatArray]]


def _identity(p: FloatArray) -> FloatArray:
    return p


def _scaled(gray: GrayImage, f: float) -> Variant:
    interp = cv2.INTER_CUBIC if f > 1 else cv2.INTER_AREA
    img = cv2.resize(gray, None, fx=f, fy=f, interpolation=interp)
    sx = img.shape[1] / gray.shape[1]
    sy = img.shape[0] / gray.shape[0]

    def back(p: FloatArray) -> FloatArray:
        result: FloatArray = (p + 0.5) / np.array([sx, sy]) - 0.5
        return result

    return np.asarray(img, np.uint8), back


def _rotated(gray: GrayImage, angle_deg: float) -> Variant:
    h, w = gray.shape
    m = cv2.getRotationMatrix2D(((w - 1) / 2, (h - 1) / 2), angle_deg, 1.0)
    cos, sin = abs(m[0, 0]), abs(m[0, 1])
    nw, nh = int(np.ceil(w * cos + h * sin)), int(np.ceil(w * sin + h * cos))
    m[0, 2] += (nw - w) / 2
    m[1, 2] += (nh - h) / 2
    img = cv2.warpAffine(gray, m, (nw, nh), flags=cv2.INTER_LINEAR, borderValue=255)
    inv = cv2.invertAffineTransform(m)

    def back(p: FloatArray) -> FloatArray:
        result: FloatArray = p @ inv[:, :2].T + inv[:, 2]
        return result

    return np.asarray(img, np.uint8), back


def _variants(gray: GrayImage) -> list[tuple[str, Callable[[], Variant]]]:
    small = min(gray.shape) < 500
    large = min(gray.shape) > 900
    out: list[tuple[str, Callable[[], Variant]]] = []
    if small:
        out.append(("up2", lambda: _scaled(gray, 2.0)))
    if large or not small:
        out.append(("down2", lambda: _scaled(gray, 0.5)))
    out.append(("blur", lambda: (np.asarray(cv2.GaussianBlur(gray, (0, 0), 1.2)), _identity)))
    out.append(("sharpen", lambda: (_sharpen(gray), _identity)))
    out.append(("adaptive", lambda: (_adaptive(gray), _identity)))
    out.append(("invert", lambda: (np.asarray(255 - gray, np.uint8), _identity)))
    out.append(("rot45", lambda: _rotated(gray, 45.0)))
    if small:
        out.append(("up3", lambda: _scaled(gray, 3.0)))
    return out


def _sharpen(gray: GrayImage) -> GrayImage:
    blurred = cv2.GaussianBlur(gray, (0, 0), 2.0)
    return np.asarray(cv2.addWeighted(gray, 2.0, blurred, -1.0, 0), np.uint8)


def _adaptive(gray: GrayImage) -> GrayImage:
    block = max(11, (min(gray.shape) // 12) | 1)
    return np.asarray(
        cv2.adaptiveThreshold(gray, 255, cv2.ADAPTIVE_THRESH_MEAN_C, cv2.THRESH_BINARY, block, 5),
        np.uint8,
    )


# --- corner order --------------------------------------------------------------------------


def _clockwise(quad: FloatArray) -> FloatArray:
    """The quad in clockwise order on the screen (v down), starting from its first corner."""
    x, y = quad[:, 0], quad[:, 1]
    area2 = float(np.sum(x * y[_NEXT] - x[_NEXT] * y))
    # With v pointing down, a positive shoelace sum is clockwise on the screen.
    if area2 < 0:
        return np.asarray(quad[[0, 3, 2, 1]], np.float64)
    return quad


_RECT = 280  # rectified side in pixels


def _finder_scores(gray: GrayImage, quad: FloatArray) -> FloatArray:
    """A misfit (4,) of each corner's diagonal to a finder pattern's 1:1:3:1:1 (low = finder)."""
    s = _RECT
    dst = np.array([[0, 0], [s, 0], [s, s], [0, s]], np.float32) - 0.5
    h = cv2.getPerspectiveTransform(quad.astype(np.float32), dst)
    rect = cv2.warpPerspective(
        gray, h, (s, s), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE
    )
    thr, _ = cv2.threshold(rect, 0, 255, cv2.THRESH_BINARY + cv2.THRESH_OTSU)
    scores = np.zeros(4)
    for k in range(4):
        # rotate so that corner k is at the top-left of the rectified image
        img = np.rot90(rect, k)
        n = s // 2
        t = np.arange(n)
        band = np.stack([img[np.clip(t + d, 0, s - 1), t] for d in (-2, 0, 2)])
        dark = band.mean(axis=0) < thr
        scores[k] = _finder_misfit(dark)
    return scores


def _finder_misfit(dark: NDArray[np.bool_]) -> float:
    # runs along the diagonal, starting at the corner
    change = np.flatnonzero(np.diff(dark.astype(np.int8))) + 1
    edges = np.concatenate([[0], change, [dark.size]])
    lengths = np.diff(edges)
    first_dark = bool(dark[0])
    if not first_dark:
        # allow a thin light sliver at the very corner (rough corner position)
        if lengths[0] > 0.05 * dark.size or lengths.size < 2:
            return 10.0
        lengths = lengths[1:]
    if lengths.size < 6:
        return 10.0
    runs = lengths[:5].astype(np.float64)
    unit = runs.sum() / 7.0
    expected = np.array([1, 1, 3, 1, 1], np.float64) * unit
    return float(np.abs(runs - expected).sum() / runs.sum())


# Rotations, by rotation index k (the corner at the rectified top-left after np.rot90(rect, k)):
# rot90 turns counter-clockwise, so rotation k brings corner index k (clockwise 0..3: TL, TR,
# BR, BL of the quad) to the top-left.


def order_corners(gray: GrayImage, quad: FloatArray) -> tuple[FloatArray, bool]:
    """``quad`` (4, 2) in any order -> (c0..c3 per docs/conventions.md, confident).

    ``confident`` is False when the finder-pattern test was ambiguous; the caller may then use
    a decoder's own orientation.
    """
    q = _clockwise(np.asarray(quad, np.float64))
    scores = _finder_scores(gray, q)
    order = np.argsort(scores)
    c2 = int(order[3])
    confident = bool(scores[order[3]] > 0.45 and scores[order[2]] < 0.45)
    c0 = (c2 + 2) % 4
    return np.asarray(np.roll(q, -c0, axis=0), np.float64), confident


# --- sub-pixel corners ---------------------------------------------------------------------


# The line fit's band half-widths, in units of its tolerance, round by round (the distances
# kept are -limit < d in the first round, -limit < d < 3 limit after it: halving from 12 with
# a floor of 1), and the first round at which a side whose kept points no longer change is
# done. Leaving out the 6 round gave the same fits on the QR photographs and renders but not on
# synthetic sides with deep outliers (test_qr_refine): kept (measured, rejected).
_BAND_SCHEDULE = (12.0, 6.0, 3.0, 1.5, 1.0, 1.0)
_FIRST_CHECK = 3


def _line_fits(
    x: FloatArray, y: FloatArray, valid: NDArray[np.bool_], tol: float
) -> list[tuple[float, float, float]] | None:
    """Lines ``(a, b, c)`` with a*x + b*y + c = 0, (a, b) a unit normal with b >= 0, fitted
    (orthogonal least squares) to each side's points ``(x, y)`` (4, n) where ``valid`` (4, n)
    with one-sided outlier removal; None when a side keeps fewer than 4 points.

    Coordinates are each side's own: x along it, y (px) outward across it, so outliers (the
    crossings a module or more inside, where the outermost module is light) have y well
    below the line. A side's fit is invariant to that rigid change of frame: the lines are
    those a fit in image coordinates would give. The moments and distances of all four sides
    are one matrix product per round, the line from a side's six moments plain float
    arithmetic (issue 19's speed goal). Each side stops at its own convergence, as a fit of
    that side alone would.
    """
    # the points without a crossing are put far inside, where no round's band keeps them:
    # the kept set is then the band test alone (one array operation fewer per round)
    y = np.where(valid, y, -1e6)
    keep = valid
    moments = np.empty(x.shape + (6,))
    moments[:, :, 0] = 1.0
    moments[:, :, 1] = x
    moments[:, :, 2] = y
    np.multiply(x, x, out=moments[:, :, 3])
    np.multiply(y, y, out=moments[:, :, 4])
    np.multiply(x, y, out=moments[:, :, 5])
    homogeneous = moments[:, :, :3]  # (1, x, y): a line (c, a, b) gives the distance
    done = [False] * 4
    lines = [(0.0, 0.0, 0.0)] * 4  # (a, b, c)
    # A side is done when a round's band keeps the very points its line was fitted to; that
    # shows as the next round's sums equal to this round's (no comparison of the point sets)
    previous: list[list[list[float]]] | None = None
    last = len(_BAND_SCHEDULE) - 1
    for it, factor in enumerate(_BAND_SCHEDULE):
        # (the kept points' weights are the booleans as 1.0 and 0.0)
        sums = np.matmul(keep[:, None, :], moments).tolist()
        for k in range(4):
            if done[k]:
                continue
            if previous is not None and sums[k] == previous[k]:
                done[k] = True
                continue
            count, su, sv, suu, svv, suv = sums[k][0]
            if count < 4:
                return None
            cu, cv = su / count, sv / count
            suu -= count * cu * cu
            svv -= count * cv * cv
            suv -= count * cu * cv
            # the 2x2 scatter's major axis is at 0.5 * atan2(2 suv, suu - svv): the line's
            # direction; the normal is perpendicular to it, turned outward (b >= 0)
            theta = 0.5 * math.atan2(2.0 * suv, suu - svv)
            nu, nv = -math.sin(theta), math.cos(theta)
            if nv < 0:
                nu, nv = -nu, -nv
            lines[k] = (nu, nv, -(nu * cu + nv * cv))
        if it == last or all(done):
            break
        previous = sums if it >= _FIRST_CHECK else None
        limit = factor * tol
        # the band: -limit < distance (> 0 outward) in the first round; from the second on
        # also < 3 limit, a symmetric clean-up of outward noise (bad samples near glare,
        # clutter), i.e. |distance - limit| < 2 limit. The shift is folded into the lines.
        shift = -limit if it > 0 else limit
        cab = np.array([v for a, b, c in lines for v in (c + shift, a, b)]).reshape(4, 3, 1)
        shifted = np.matmul(homogeneous, cab)[:, :, 0]  # (4, n)
        keep = np.abs(shifted) < 2.0 * limit if it > 0 else shifted > 0.0
    return lines


# Sample spacing along a profile (px) and remap's limit on a map's columns (OpenCV's SHRT_MAX).
_STEP = 0.25
_REMAP_COLS = 32767


@lru_cache(maxsize=128)
def _fractions(n_samples: int) -> FloatArray:
    """Where ``n_samples`` profiles cross a side: fractions of its length from its first corner
    (the ends are left out, where the neighbouring side's quiet zone would be sampled); cached,
    since the same few counts recur (issue 19's speed goal)."""
    t = 0.06 + (0.88 / (n_samples - 1)) * np.arange(n_samples, dtype=np.float64)
    t.flags.writeable = False
    return t


@lru_cache(maxsize=128)
def _fractions32(n_samples: int) -> NDArray[np.float32]:
    t = _fractions(n_samples).astype(np.float32)
    t.flags.writeable = False
    return t


# the sample indices along a profile, sliced for the profiles of all but huge codes
_STEPS = np.arange(1024, dtype=np.float32).reshape(1, -1, 1, 1)
_STEPS.flags.writeable = False


def _edge_offsets(
    gray: NDArray[np.float32], coef: list[float], s_first: float, n_steps: int, n_samples: int
) -> tuple[FloatArray, NDArray[np.bool_]]:
    """Sub-pixel mid-level crossings on ``n_samples`` profiles across each of the four sides at
    :func:`_fractions` along them (outside to inside, ``n_steps`` samples each): their offsets
    (4, n) in px outward from the rough side, and which of them were found (4, n).

    ``coef`` (24 floats) holds three (2, 4) blocks, u row then v row, one column per side: the
    sides' first corners moved ``s_first`` px outward (the outermost offset), the side vectors,
    and the step between samples (``-_STEP`` times the outward unit normals); sample j of
    profile i of side k lies at block0 + t_i block1 + j block2 (px in ``gray``).

    Its cost is per-call overhead (issue 19's speed goal), so the four sides are one array all
    along, laid out (offsets, profiles) with profile k n + i for sample i of side k: the long
    axis innermost, where numpy's loops are fast, and every per-profile statistic a reduction
    across rows. One cv2.remap reads all samples.
    """
    n_prof = 4 * n_samples
    blocks = np.array(coef, np.float32).reshape(3, 2, 4, 1)
    feet = blocks[0] + blocks[1] * _fractions32(n_samples)  # (2, 4, n)
    if n_steps <= _STEPS.shape[1]:
        steps = _STEPS[:, :n_steps]
    else:
        steps = np.arange(n_steps, dtype=np.float32).reshape(1, -1, 1, 1)
    positions = feet[:, None] + steps * blocks[2][:, None]  # (2, n_steps, 4, n): u, v
    # one row when it fits: OpenCV splits a remap of several rows across its threads, and on
    # a loaded machine waiting for them costs more than the read
    total = n_steps * n_prof
    shape = (1, total) if total <= _REMAP_COLS else (n_steps, n_prof)
    prof = np.asarray(
        cv2.remap(
            gray,
            positions[0].reshape(shape),
            positions[1].reshape(shape),
            cv2.INTER_LINEAR,
            borderMode=cv2.BORDER_REPLICATE,
        ),
        np.float32,
    ).reshape(n_steps, n_prof)
    # light: the median of the outer fifth (the quiet zone); dark: the profile's minimum.
    # (OpenCV's column sort takes half the time of np.sort along the first axis.)
    nq = max(2, n_steps // 5)
    outer = np.asarray(cv2.sort(prof[:nq], cv2.SORT_EVERY_COLUMN | cv2.SORT_ASCENDING))
    light = (outer[(nq - 1) // 2] + outer[nq // 2]) / 2
    dark = prof.min(axis=0)
    contrast = (light - dark).reshape(4, n_samples)
    ranked = np.asarray(cv2.sort(contrast, cv2.SORT_EVERY_ROW | cv2.SORT_ASCENDING))
    typical = (ranked[:, (n_samples - 1) // 2] + ranked[:, n_samples // 2]) / 2
    level = (light + dark) / 2
    first = np.argmax(prof < level, axis=0)
    # first > 0 also says that some sample is below the level (argmax is 0 when none is)
    valid = (contrast > 0.5 * typical[:, None]) & (first > 0).reshape(4, n_samples)
    # the samples first - 1 (at or above the level) and first (below it), by flat index; where
    # first is 0 the index wraps to the last row: a finite value for a point not found
    at = first * n_prof + np.arange(n_prof)
    v1 = prof.reshape(total)[at]
    v0 = prof.reshape(total)[at - n_prof]
    # v0 >= level > v1 where found, so the fraction lies in [0, 1] there without a clip
    frac = (v0 - level) / np.maximum(v0 - v1, 1e-6)
    s_cross = (s_first + _STEP) - _STEP * (first + frac)
    return s_cross.reshape(4, n_samples), valid


def refine_corners(
    gray: GrayImage, corners: FloatArray, *, modules: int | None = None
) -> FloatArray:
    """Sub-pixel outer corners from rough ``corners`` (4, 2) in clockwise order.

    Returns the rough corners unchanged where a side has too few edge points.
    """
    q = np.asarray(corners, np.float64)
    # the quad's geometry in plain floats: a dozen numpy operations on (4, 2) arrays cost
    # more than the arithmetic (issue 19's speed goal)
    pts = q.tolist()
    edges = [(pts[j][0] - pts[i][0], pts[j][1] - pts[i][1]) for i, j in enumerate(_NEXT)]
    lengths = [math.hypot(du, dv) for du, dv in edges]
    if min(lengths) < 1e-9:
        return q.copy()
    side = sum(lengths) / 4
    module = side / (modules if modules else 25)
    reach = min(max(2.5, 0.8 * module, 0.03 * side), max(2.5, 0.2 * side))
    # Convert only the code's neighbourhood to float: converting a multi-megapixel photograph
    # cost several times the decode itself (issue 19's speed goal).
    margin = reach + 3.0
    height, width = gray.shape
    us, vs = [p[0] for p in pts], [p[1] for p in pts]
    u0 = min(max(math.floor(min(us) - margin), 0), width - 1)
    v0 = min(max(math.floor(min(vs) - margin), 0), height - 1)
    u1 = min(max(math.ceil(max(us) + margin) + 1, u0 + 1), width)
    v1 = min(max(math.ceil(max(vs) + margin) + 1, v0 + 1), height)
    g = gray[v0:v1, u0:u1].astype(np.float32)
    # profiles from s_first = -reach + step (n_steps - 1) (outside, s > 0 outward) down to
    # -reach (inside)
    n_steps = math.ceil((2.0 * reach + _STEP / 2) / _STEP)
    s_first = -reach + _STEP * (n_steps - 1)
    # the normal (dv, -du) of each side points outward for a clockwise quad on the screen;
    # the test against the centre keeps a counter-clockwise one right as well
    cu, cv = sum(us) / 4, sum(vs) / 4
    outward = []
    starts_u, starts_v, steps_u, steps_v = [], [], [], []
    for (pu, pv), (du, dv), length in zip(pts, edges, lengths, strict=True):
        nu, nv = dv / length, -du / length
        if nu * (pu + 0.5 * du - cu) + nv * (pv + 0.5 * dv - cv) < 0:
            nu, nv = -nu, -nv
        outward.append((nu, nv))
        starts_u.append(pu - u0 + s_first * nu)
        starts_v.append(pv - v0 + s_first * nv)
        steps_u.append(-_STEP * nu)
        steps_v.append(-_STEP * nv)
    coef = starts_u + starts_v + [e[0] for e in edges] + [e[1] for e in edges] + steps_u + steps_v
    n_samples = int(min(max(max(lengths) / 1.5, 12.0), 120.0))
    offsets, valid = _edge_offsets(g, coef, s_first, n_steps, n_samples)
    # each side's own frame: x along it from its midpoint, y = the offset outward
    x = np.array(lengths)[:, None] * (_fractions(n_samples) - 0.5)
    fits = _line_fits(x, offsets, valid, tol=max(0.35, 0.3 * module))
    if fits is None:
        return q.copy()
    # back to image coordinates: p = m + x e + y o (m the side's midpoint, e its unit
    # direction, o the outward normal), so the line is (a e + b o) . (p - m) + c = 0
    rows = []
    for (pu, pv), (du, dv), length, (ou, ov), (a, b, c) in zip(
        pts, edges, lengths, outward, fits, strict=True
    ):
        nu = a * du / length + b * ou
        nv = a * dv / length + b * ov
        rows.append((nu, nv, c - nu * (pu + 0.5 * du) - nv * (pv + 0.5 * dv)))
    # corner i is where the sides i - 1 and i meet: the cross product of their lines
    meets = []
    limit2 = max(3.0, 0.1 * side) ** 2
    for i in range(4):
        (a1, b1, c1), (a2, b2, c2) = rows[_PREV[i]], rows[i]
        w = a1 * b2 - b1 * a2
        if abs(w) < 1e-12:
            return q.copy()
        mu, mv = (b1 * c2 - c1 * b2) / w, (c1 * a2 - a1 * c2) / w
        if (mu - pts[i][0]) ** 2 + (mv - pts[i][1]) ** 2 > limit2:
            return q.copy()
        meets.append((mu, mv))
    return np.array(meets)


# --- the reader ----------------------------------------------------------------------------


def gray_for_code(
    image: NDArray[np.generic], *, min_side: int = 21, what: str = "a QR code"
) -> GrayImage:
    """``image`` (uint8 gray, BGR or BGRA) as a contiguous gray image; BadImageError when it is
    not one, or smaller than ``min_side`` pixels a side (too small for ``what``)."""
    arr = np.asarray(image)
    if arr.dtype != np.uint8:
        raise BadImageError(f"image must be uint8, got {arr.dtype}")
    if arr.ndim == 3 and arr.shape[2] == 1:
        arr = arr[:, :, 0]
    if arr.ndim == 3 and arr.shape[2] in (3, 4):
        code = cv2.COLOR_BGR2GRAY if arr.shape[2] == 3 else cv2.COLOR_BGRA2GRAY
        arr = cv2.cvtColor(arr, code)
    if arr.ndim != 2:
        raise BadImageError(f"image must be (H, W) or (H, W, 3), got shape {arr.shape}")
    if arr.shape[0] < min_side or arr.shape[1] < min_side:
        raise BadImageError(f"image too small for {what}: {arr.shape[1]}x{arr.shape[0]}")
    return np.ascontiguousarray(arr)


def crop_for_code(
    gray: GrayImage, roi: Sequence[int] | None, *, min_side: int = 21, what: str = "a QR code"
) -> tuple[GrayImage, FloatArray]:
    """The ``roi`` ``[u, v, width, height]`` of ``gray`` and its offset (pixels); RoiError when
    it is malformed, outside the image or smaller than ``min_side`` a side."""
    if roi is None:
        return gray, np.zeros(2)
    if len(roi) != 4:
        raise RoiError(f"roi must be [u, v, width, height], got {roi!r}")
    u, v, w, h = (int(x) for x in roi)
    height, width = gray.shape
    if w <= 0 or h <= 0:
        raise RoiError(f"roi {list(roi)} is empty")
    if u < 0 or v < 0 or u + w > width or v + h > height:
        raise RoiError(f"roi {list(roi)} does not lie inside the {width}x{height} image")
    if w < min_side or h < min_side:
        raise RoiError(f"roi {list(roi)} is too small for {what}")
    return np.ascontiguousarray(gray[v : v + h, u : u + w]), np.array([u, v], np.float64)


def _merge(found: list[_Raw], new: list[_Raw]) -> None:
    for r in new:
        if not found:  # the common case: nothing to compare with
            found.append(r)
            continue
        side = float(np.mean(np.linalg.norm(r.quad - r.quad[_NEXT], axis=1)))
        for f in found:
            if f.text == r.text and np.linalg.norm(f.quad.mean(0) - r.quad.mean(0)) < 0.5 * side:
                f.hits += 1
                if f.version is None:
                    f.version = r.version
                break
        else:
            found.append(r)


def decode_raw(
    gray: GrayImage, decoders: Sequence[str], expect: Expect = None, *, preprocess: bool = True
) -> tuple[list[_Raw], list[str]]:
    """Run ``decoders`` on ``gray`` (then on preprocessed copies while nothing matching
    ``expect`` is found). Returns the raw detections (quads in ``gray`` pixels, any order)
    and the list of what was tried."""
    found: list[_Raw] = []
    tried: list[str] = []

    def done() -> bool:
        return any(matches(f.text, expect) for f in found)

    for name in decoders:
        tried.append(name)
        _merge(found, DECODERS[name](gray))
        if done():  # escalate to a slower decoder only when the faster ones found nothing
            return found, tried
    if done() or not preprocess:
        return found, tried
    cheap = [d for d in decoders if d in ("zxing", "pyzbar")]
    for label, make in _variants(gray):
        img, back = make()
        for name in cheap:
            tried.append(f"{name}+{label}")
            for r in DECODERS[name](img):
                r.quad = back(r.quad)
                r.decoder = f"{name}+{label}"
                _merge(found, [r])
            if done():
                return found, tried
    return found, tried


def read_qr(
    image: NDArray[np.generic],
    *,
    roi: Sequence[int] | None = None,
    expect: Expect = None,
    decoders: Sequence[str] = ("zxing", "pyzbar", "opencv", "opencv_aruco"),
    refine: bool = True,
) -> list[QRCode]:
    """Find and decode the QR codes in ``image`` (uint8 gray or BGR; (u, v) pixels).

    ``roi`` ``[u, v, width, height]`` restricts the search; ``expect`` (an exact string or a
    compiled pattern that must match the whole text) selects codes. Returns the codes best
    first (found by more decoders / preprocessings, then larger), corners in full-image pixels,
    c0..c3 as printed, sub-pixel refined unless ``refine=False``.

    Raises BadImageError, RoiError, or NotFoundError (naming what was tried) when nothing
    decodes or nothing matches ``expect``.
    """
    for name in decoders:
        if name not in DECODERS:
            raise ValueError(f"unknown decoder {name!r}; known: {', '.join(sorted(DECODERS))}")
    gray_full = gray_for_code(image)
    gray, offset = crop_for_code(gray_full, roi)
    found, tried = decode_raw(gray, decoders, expect)
    codes: list[tuple[int, float, QRCode]] = []
    for r in found:
        if not matches(r.text, expect):
            continue
        if r.decoder.startswith("zxing") and "rot" not in r.decoder:
            # zxing-cpp reports the corners in symbol order (top-left = the finder pattern
            # opposite the corner without one): the image test would only repeat it, at twice
            # the cost of the decode. (_clockwise keeps the first corner first.)
            ordered = _clockwise(r.quad)
        else:
            ordered, confident = order_corners(gray, r.quad)
            if not confident and r.decoder.startswith("opencv") and "rot" not in r.decoder:
                # OpenCV reports corners in symbol order too: trust it when the test is unsure
                ordered = _start_at(_clockwise(r.quad), r.quad[0])
        modules = 17 + 4 * r.version if r.version else None
        if refine:
            ordered = refine_corners(gray, ordered, modules=modules)
        area = float(cv2.contourArea(ordered.astype(np.float32)))
        codes.append((r.hits, area, QRCode(r.text, ordered + offset, r.decoder, modules)))
    if not codes:
        what = "any QR code" if expect is None else f"a QR code matching {describe(expect)}"
        seen = sorted({r.text for r in found})
        extra = f"; decoded instead: {seen}" if seen else ""
        raise NotFoundError(f"no {what} found (tried {', '.join(tried)}){extra}")
    codes.sort(key=lambda c: (-c[0], -c[1]))
    return [c[2] for c in codes]


def _start_at(quad: FloatArray, first: FloatArray) -> FloatArray:
    k = int(np.argmin(np.linalg.norm(quad - first, axis=1)))
    return np.asarray(np.roll(quad, -k, axis=0), np.float64)
