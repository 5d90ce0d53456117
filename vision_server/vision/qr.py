"""QR-code reading: several decoders and preprocessing steps, corners in the documented order.

The corners follow docs/conventions.md: ``c0`` top-left (a finder pattern's corner), ``c1``
top-right, ``c2`` bottom-right (the corner without a finder pattern), ``c3`` bottom-left, as the
code is printed, i.e. clockwise in an image of the code seen from the front. They are the outer
corners of the symbol's dark modules (without the quiet zone), in ``(u, v)`` full-image pixels,
refined to sub-pixel accuracy by fitting straight lines to the symbol's four outer edges.

Each decoder reports corners in its own order and accuracy; the order used here does not rely
on it: the corner without a finder pattern is found in the image (it becomes ``c2``, and ``c0``
is the opposite corner), and only the handedness (which neighbour of ``c0`` is ``c1``) comes from
the decoder, which knows it from the symbol's contents (a mirrored image is reported as such).
"""

from __future__ import annotations

import re
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass

import cv2
import numpy as np
import zxingcpp
from numpy.typing import NDArray
from pyzbar import pyzbar

from vision_server.vision._checks import as_gray, check_roi, crop
from vision_server.vision.errors import ParameterError

__all__ = ["DECODERS", "QrCode", "read_qr"]

FloatArray = NDArray[np.float64]
GrayImage = NDArray[np.uint8]

DECODERS = ("pyzbar", "zxing", "opencv")
"""The decoders ``read_qr`` can use, in the order it tries them."""


@dataclass(frozen=True)
class QrCode:
    """One decoded QR code.

    Attributes
    ----------
    text : str
        The payload.
    corners : (4, 2) ndarray of float64
        ``c0, c1, c2, c3`` (top-left, top-right, bottom-right, bottom-left as printed) as
        ``(u, v)`` full-image pixels.
    refined : bool
        True when the corners come from the edge-line fit; False when they are the decoder's
        (e.g. too few edge points were found, as on a very small or blurred code).
    mirrored : bool
        True when the code appears mirrored in the image (counter-clockwise ``c0..c3``).
    modules : int
        Modules per side (21 for version 1, ... 177), as estimated from the image or the decoder.
    decoder : str
        Which decoder read it: ``"pyzbar"``, ``"zxing"`` or ``"opencv"``.
    preprocessing : str
        The preprocessing of the image that the decoder succeeded on (``"none"`` if none).
    """

    text: str
    corners: FloatArray
    refined: bool
    mirrored: bool
    modules: int
    decoder: str
    preprocessing: str

    @property
    def center(self) -> FloatArray:
        """The mean of the four corners ``(u, v)`` in pixels."""
        return np.asarray(self.corners.mean(axis=0), dtype=np.float64)


@dataclass(frozen=True)
class _Raw:
    """A decoder's answer: text, corners in the decoder's symbol order, its version if known."""

    text: str
    corners: FloatArray  # (4, 2) in the decoder's order (see _symbol_order)
    decoder: str
    modules: int | None


# ---------------------------------------------------------------------------------------------
# decoders (each returns corners in symbol order c0..c3, start corner possibly wrong)


def _decode_pyzbar(gray: GrayImage) -> list[_Raw]:
    out: list[_Raw] = []
    for r in pyzbar.decode(gray, symbols=[pyzbar.ZBarSymbol.QRCODE]):
        pts = np.array([(p.x, p.y) for p in r.polygon], dtype=np.float64)
        if pts.shape != (4, 2):
            continue
        # zbar lists the corners with the opposite handedness to the symbol's c0..c3 (measured
        # on rendered codes); its start corner is arbitrary, which the finder check fixes.
        out.append(_Raw(r.data.decode("utf-8", errors="replace"), pts[::-1].copy(), "pyzbar", None))
    if any(not raw.text.isascii() for raw in out):
        # zbar guesses the character set of non-ASCII payloads and often guesses wrong (e.g.
        # Shift-JIS half-width katakana); zxing-cpp honours ECI and guesses better, so its text
        # wins for a code both decoders find at the same place.
        others = _decode_zxing(gray)
        for i, raw in enumerate(out):
            size = float(np.linalg.norm(raw.corners[0] - raw.corners[2]))
            for other in others:
                if np.linalg.norm(other.corners.mean(0) - raw.corners.mean(0)) < 0.3 * size:
                    out[i] = _Raw(other.text, raw.corners, raw.decoder, other.modules)
    return out


def _decode_zxing(gray: GrayImage, binarizer: zxingcpp.Binarizer | None = None) -> list[_Raw]:
    chosen = zxingcpp.Binarizer.LocalAverage if binarizer is None else binarizer
    results = zxingcpp.read_barcodes(
        gray,
        formats=zxingcpp.BarcodeFormats(zxingcpp.BarcodeFormat.QRCode),
        text_mode=zxingcpp.TextMode.Plain,
        binarizer=chosen,
    )
    out: list[_Raw] = []
    for r in results:
        p = r.position
        pts = np.array(
            [(q.x, q.y) for q in (p.top_left, p.top_right, p.bottom_right, p.bottom_left)],
            dtype=np.float64,
        )
        modules: int | None = None
        version = r.extra.get("Version") if isinstance(r.extra, dict) else None
        if isinstance(version, str) and version.isdigit():
            modules = 17 + 4 * int(version)
        out.append(_Raw(r.text, pts, "zxing", modules))
    return out


def _decode_zxing_histogram(gray: GrayImage) -> list[_Raw]:
    return _decode_zxing(gray, zxingcpp.Binarizer.GlobalHistogram)


def _decode_opencv(gray: GrayImage) -> list[_Raw]:
    out: list[_Raw] = []
    for detector in (cv2.QRCodeDetectorAruco(), cv2.QRCodeDetector()):
        try:
            ok, texts, points, _ = detector.detectAndDecodeMulti(gray)
        except (cv2.error, UnicodeDecodeError):  # unsupported modes or charsets in OpenCV
            continue
        if not ok or points is None:
            continue
        for text, pts in zip(texts, points, strict=False):
            if text:
                arr = np.asarray(pts, dtype=np.float64).reshape(4, 2)
                out.append(_Raw(str(text), arr, "opencv", None))
        if out:
            break
    return out


# ---------------------------------------------------------------------------------------------
# preprocessing steps: (name, function, scale of the result relative to the input)


def _preprocessings(gray: GrayImage) -> Iterator[tuple[str, NDArray[np.generic], float]]:
    height, width = gray.shape
    yield "downscale0.5", cv2.resize(gray, None, fx=0.5, fy=0.5, interpolation=cv2.INTER_AREA), 0.5
    yield "blur", cv2.GaussianBlur(gray, (3, 3), 0), 1.0
    if max(height, width) < 800:
        up = cv2.resize(gray, None, fx=2.0, fy=2.0, interpolation=cv2.INTER_CUBIC)
        yield "upscale2", up, 2.0
    blurred = cv2.GaussianBlur(gray, (0, 0), 2.0)
    yield "sharpen", cv2.addWeighted(gray, 2.0, blurred, -1.0, 0), 1.0
    yield "clahe", cv2.createCLAHE(clipLimit=3.0, tileGridSize=(8, 8)).apply(gray), 1.0
    block = max(15, (min(height, width) // 16) | 1)
    adaptive = cv2.adaptiveThreshold(
        gray, 255, cv2.ADAPTIVE_THRESH_GAUSSIAN_C, cv2.THRESH_BINARY, block, 5
    )
    yield "adaptive", adaptive, 1.0
    yield "median", cv2.medianBlur(gray, 3), 1.0
    yield "inverted", cv2.bitwise_not(gray), 1.0


# ---------------------------------------------------------------------------------------------
# corner order and sub-pixel refinement


def _signed_area(quad: FloatArray) -> float:
    """Shoelace area; positive when the points run clockwise on the screen (v down)."""
    u, v = quad[:, 0], quad[:, 1]
    return 0.5 * float(np.sum(u * np.roll(v, -1) - np.roll(u, -1) * v))


def _finder_template(size: int) -> FloatArray:
    """The ideal 8x8-module corner (finder pattern + separator), 1 = dark, at ``size`` px/module."""
    m = np.zeros((8, 8))
    m[0:7, 0:7] = 1.0
    m[1:6, 1:6] = 0.0
    m[2:5, 2:5] = 1.0
    return np.asarray(np.kron(m, np.ones((size, size))), dtype=np.float64)


_CANON = 420  # side in pixels of the canonical (rectified) view of a code
_TEMPLATE_PX = 4


def _rectify(gray: FloatArray, quad: FloatArray) -> FloatArray:
    """The code rectified to a ``_CANON`` square, quad corner k at canonical corner k."""
    dst = np.array([[0, 0], [_CANON, 0], [_CANON, _CANON], [0, _CANON]], dtype=np.float64) - 0.5
    h = cv2.getPerspectiveTransform(quad.astype(np.float32), dst.astype(np.float32))
    return np.asarray(
        cv2.warpPerspective(gray.astype(np.float32), h, (_CANON, _CANON), flags=cv2.INTER_LINEAR),
        dtype=np.float64,
    )


def _finder_scores(rect: FloatArray, modules: Sequence[int]) -> tuple[FloatArray, int]:
    """Correlation of each canonical corner with a finder pattern, and the best module count."""
    template = _finder_template(_TEMPLATE_PX).ravel()
    template = (template - template.mean()) / template.std()
    size = 8 * _TEMPLATE_PX
    best = np.full(4, -1.0)
    best_total = -np.inf
    best_n = int(modules[0])
    for n in modules:
        extent = 8.0 * _CANON / n
        k = int(round(extent))
        if k < 8 or k > _CANON // 2:
            continue
        views = (
            rect[:k, :k],
            rect[:k, ::-1][:, :k],
            rect[::-1, ::-1][:k, :k],
            rect[::-1, :][:k, :k],
        )
        scores = np.empty(4)
        for i, view in enumerate(views):
            patch = cv2.resize(
                np.ascontiguousarray(view), (size, size), interpolation=cv2.INTER_AREA
            ).ravel()
            patch = -(patch - patch.mean())  # dark = positive
            sd = patch.std()
            scores[i] = float(patch @ template) / (sd * template.size) if sd > 0 else 0.0
        total = float(np.sort(scores)[1:].sum())  # the three best corners carry finders
        if total > best_total:
            best_total, best, best_n = total, scores, int(n)
    return best, best_n


def _edge_points(
    gray: FloatArray, p: FloatArray, q: FloatArray, inward: FloatArray, half: float
) -> FloatArray:
    """Sub-pixel points of the light-to-dark (going inward) edge along the segment p->q."""
    length = float(np.linalg.norm(q - p))
    count = max(8, int(length / 1.5))
    ts = np.linspace(0.03, 0.97, count)
    step = 0.25
    offsets = np.arange(-half, half + step / 2, step)
    base = p[None, :] + ts[:, None] * (q - p)[None, :]
    samples = base[:, None, :] + offsets[None, :, None] * inward[None, None, :]
    profile = cv2.remap(
        gray.astype(np.float32),
        samples[..., 0].astype(np.float32),
        samples[..., 1].astype(np.float32),
        interpolation=cv2.INTER_LINEAR,
        borderMode=cv2.BORDER_REPLICATE,
    ).astype(np.float64)
    kernel = np.array([1.0, 4.0, 6.0, 4.0, 1.0]) / 16.0
    smooth = cv2.filter2D(profile, -1, kernel[None, :], borderType=cv2.BORDER_REPLICATE)
    grad = np.zeros_like(smooth)
    grad[:, 1:-1] = (smooth[:, 2:] - smooth[:, :-2]) / 2.0  # negative where it gets darker
    contrast = np.percentile(profile, 95) - np.percentile(profile, 5)
    points: list[FloatArray] = []
    for i in range(count):
        g = -grad[i, 3:-3]
        if contrast <= 0:
            break
        strong = np.flatnonzero(g > 0.35 * contrast * step)
        if strong.size == 0:
            continue
        j = int(strong[0])
        while j + 1 < g.size and g[j + 1] >= g[j]:  # climb to the first (outermost) peak
            j += 1
        if j == 0 or j + 1 >= g.size:
            continue
        a, b, c = g[j - 1], g[j], g[j + 1]
        denom = a - 2.0 * b + c
        shift = 0.5 * (a - c) / denom if denom < 0 else 0.0
        offset = offsets[j + 3] + float(np.clip(shift, -0.5, 0.5)) * step
        points.append(base[i] + offset * inward)
    return np.array(points, dtype=np.float64).reshape(-1, 2)


def _fit_line(points: FloatArray, tolerance: float) -> tuple[FloatArray, float] | None:
    """Robust line ``n . x = d`` (unit n) through ``points`` with iterative outlier rejection."""
    if points.shape[0] < 6:
        return None
    keep = np.ones(points.shape[0], dtype=bool)
    # Start from the median-based residuals so that a row of inner edges cannot win.
    for _ in range(6):
        pts = points[keep]
        if pts.shape[0] < 6:
            return None
        centre = pts.mean(axis=0)
        _, _, vt = np.linalg.svd(pts - centre, full_matrices=False)
        normal = vt[1]
        d = float(normal @ centre)
        res = points @ normal - d
        med = float(np.median(res[keep]))
        new_keep = np.abs(res - med) <= max(tolerance, 0.0)
        if np.array_equal(new_keep, keep):
            break
        keep = new_keep
    pts = points[keep]
    if pts.shape[0] < 6:
        return None
    centre = pts.mean(axis=0)
    _, _, vt = np.linalg.svd(pts - centre, full_matrices=False)
    return vt[1], float(vt[1] @ centre)


def _intersect(l1: tuple[FloatArray, float], l2: tuple[FloatArray, float]) -> FloatArray | None:
    a = np.array([l1[0], l2[0]])
    if abs(np.linalg.det(a)) < 1e-6:
        return None
    return np.asarray(np.linalg.solve(a, np.array([l1[1], l2[1]])), dtype=np.float64)


def _refine(gray: FloatArray, quad: FloatArray, module_px: float) -> FloatArray | None:
    """Fit lines to the four outer edges of the symbol (dark side inside) and intersect them."""
    current = quad.copy()
    sign = 1.0 if _signed_area(current) > 0 else -1.0
    for half, tol in ((max(4.0, 1.2 * module_px), 1.0), (max(2.0, 0.6 * module_px), 0.5)):
        lines: list[tuple[FloatArray, float]] = []
        for k in range(4):
            p, q = current[k], current[(k + 1) % 4]
            direction = (q - p) / np.linalg.norm(q - p)
            # Inward normal: for a clockwise-on-screen quad, (-dv, du) points inside.
            inward = sign * np.array([-direction[1], direction[0]])
            pts = _edge_points(gray, p, q, inward, half)
            line = _fit_line(pts, tol * max(1.0, module_px / 4.0))
            if line is None:
                return None
            lines.append(line)
        refined = np.empty((4, 2))
        for k in range(4):
            corner = _intersect(lines[(k - 1) % 4], lines[k])
            if corner is None:
                return None
            refined[k] = corner
        if np.max(np.linalg.norm(refined - current, axis=1)) > max(6.0, 2.0 * module_px):
            return None
        current = refined
    return current


def _inside_is_dark(gray: FloatArray, quad: FloatArray) -> bool:
    centre = quad.mean(axis=0)
    inner = centre + 0.97 * (quad - centre)
    outer = centre + 1.06 * (quad - centre)
    h, w = gray.shape

    def sample(pts: FloatArray) -> float:
        u = np.clip(np.round(pts[:, 0]).astype(int), 0, w - 1)
        v = np.clip(np.round(pts[:, 1]).astype(int), 0, h - 1)
        return float(np.mean(gray[v, u]))

    return sample(inner) <= sample(outer)


def _format_codewords() -> NDArray[np.int64]:
    """The 32 valid 15-bit format-information words (BCH(15, 5), masked) of a QR symbol."""
    words = []
    for data in range(32):
        value = data << 10
        for bit in range(14, 9, -1):
            if value >> bit & 1:
                value ^= 0b10100110111 << (bit - 10)
        words.append(((data << 10) | value) ^ 0b101010000010010)
    return np.array(words, dtype=np.int64)


_FORMAT_WORDS = _format_codewords()


def _format_distance(grid: NDArray[np.bool_]) -> int:
    """Hamming distance of both format-information copies in ``grid`` to a valid word.

    ``grid`` (N, N) holds the modules (True = dark) with c0 at [0, 0]. Each copy is read most
    significant bit first: around the top-left finder along row 8 then up column 8; the second
    copy up column 8 from the bottom-left, then along row 8 to the right edge.
    """
    n = grid.shape[0]
    first = [grid[8, c] for c in (0, 1, 2, 3, 4, 5, 7, 8)] + [
        grid[r, 8] for r in (7, 5, 4, 3, 2, 1, 0)
    ]
    second = [grid[n - 1 - i, 8] for i in range(7)] + [grid[8, n - 8 + i] for i in range(8)]
    total = 0
    for bits in (first, second):
        value = int("".join("1" if b else "0" for b in bits), 2)
        total += min(bin(value ^ int(w)).count("1") for w in _FORMAT_WORDS)
    return total


def _module_grid(gray: FloatArray, quad: FloatArray, modules: int) -> NDArray[np.bool_]:
    """Dark modules (N, N) sampled at the module centres of the code with corners ``quad``."""
    rect = _rectify(gray, quad)
    centres = (np.arange(modules) + 0.5) * _CANON / modules - 0.5
    cu, cv = np.meshgrid(centres, centres)
    values = cv2.remap(
        rect.astype(np.float32),
        cu.astype(np.float32),
        cv.astype(np.float32),
        interpolation=cv2.INTER_LINEAR,
    ).astype(np.float64)
    threshold = 0.5 * (np.percentile(values, 10) + np.percentile(values, 90))
    return np.asarray(values < threshold)


def _analyse(gray: GrayImage, raw: _Raw, *, refine: bool) -> tuple[FloatArray, bool, bool, int]:
    """Order (and refine) the corners of one decoded code: (corners, refined, mirrored, N)."""
    quad = raw.corners.astype(np.float64)
    decoder_mirrored = raw.decoder != "pyzbar" and _signed_area(quad) < 0
    if _signed_area(quad) < 0:
        quad = quad[::-1].copy()  # work clockwise on the screen
    work = gray.astype(np.float64)
    if not _inside_is_dark(work, quad):
        work = 255.0 - work
    candidates = [raw.modules] if raw.modules else list(range(21, 102, 4))
    scores, modules = _finder_scores(_rectify(work, quad), candidates)
    missing = int(np.argmin(scores))
    quad = np.roll(quad, -((missing + 2) % 4), axis=0)  # c0 is opposite the finder-less corner
    # Handedness: the format information reads as a valid word only in the right one.
    grid = _module_grid(work, quad, modules)
    as_seen, transposed = _format_distance(grid), _format_distance(grid.T)
    mirrored = transposed < as_seen if transposed != as_seen else decoder_mirrored
    refined_ok = False
    if refine:
        side = float(np.mean(np.linalg.norm(quad - np.roll(quad, -1, axis=0), axis=1)))
        better = _refine(work, quad, side / modules)
        if better is not None:
            quad, refined_ok = better, True
    if mirrored:
        quad = quad[[0, 3, 2, 1]]
    return quad, refined_ok, mirrored, modules


# ---------------------------------------------------------------------------------------------
# public function


def _matches(text: str, expect: str | re.Pattern[str] | None) -> bool:
    if expect is None:
        return True
    if isinstance(expect, re.Pattern):
        return expect.fullmatch(text) is not None
    return text == expect


def read_qr(
    image: NDArray[np.uint8],
    *,
    roi: Sequence[float] | None = None,
    expect: str | re.Pattern[str] | None = None,
    decoders: Sequence[str] = DECODERS,
    preprocess: bool = True,
    refine: bool = True,
) -> tuple[QrCode, ...]:
    """Read the QR codes in ``image`` (or in its ``roi``).

    The decoders are tried on the image as it is, in the order of ``decoders``; if that finds no
    code (or none matching ``expect``), the image is preprocessed (downscaled, blurred, upscaled
    when small, sharpened, contrast-equalised, adaptively thresholded, median-filtered,
    inverted) and the decoders are tried again on each version in turn, until one succeeds.

    Parameters
    ----------
    image : (H, W) or (H, W, 3) ndarray of uint8
        Gray or BGR image.
    roi : [u, v, width, height], optional
        Where to search, in full-image pixels; the whole image by default.
    expect : str or compiled regex, optional
        Keep only codes whose text equals this string (or fully matches this pattern); the
        search goes on until such a code is found.
    decoders : sequence of str
        Subset of :data:`DECODERS`, in the order to try them.
    preprocess : bool
        Whether to try the preprocessing steps when the plain image yields nothing.
    refine : bool
        Whether to refine the corners to sub-pixel accuracy (edge-line fit).

    Returns
    -------
    tuple of QrCode
        The codes found (first found first; empty if none), corners in full-image pixels.

    Raises
    ------
    BadImageError, RoiError, ParameterError
        Invalid image, ROI or decoder name.
    """
    gray_full = as_gray(image)
    box = check_roi(roi, gray_full.shape)
    gray = np.ascontiguousarray(crop(gray_full, box))
    unknown = [d for d in decoders if d not in DECODERS]
    if unknown or not decoders:
        raise ParameterError(f"decoders must be a non-empty subset of {DECODERS}, got {decoders}")
    functions: list[Callable[[GrayImage], list[_Raw]]] = []
    for name in decoders:
        if name == "pyzbar":
            functions.append(_decode_pyzbar)
        elif name == "zxing":
            functions += [_decode_zxing, _decode_zxing_histogram]
        else:
            functions.append(_decode_opencv)

    found: list[QrCode] = []

    def add(raws: list[_Raw], scale: float, step: str) -> None:
        for raw in raws:
            if not _matches(raw.text, expect):
                continue
            corners = (raw.corners + 0.5) / scale - 0.5
            raw = _Raw(raw.text, corners, raw.decoder, raw.modules)
            centre = corners.mean(axis=0)
            side = float(np.linalg.norm(corners[0] - corners[2]))
            if any(
                q.text == raw.text and np.linalg.norm(q.center - box[:2] - centre) < 0.3 * side
                for q in found
            ):
                continue
            quad, refined, mirrored, modules = _analyse(gray, raw, refine=refine)
            quad = quad + np.array(box[:2], dtype=np.float64)
            found.append(QrCode(raw.text, quad, refined, mirrored, modules, raw.decoder, step))

    for function in functions:
        add(function(gray), 1.0, "none")
        if found:
            # One decoder's success ends the search; the first decoder is the most reliable.
            return tuple(found)
    if preprocess:
        # OpenCV's detectors are slow and never added a decode on preprocessed images of the
        # real test set; preprocessing goes to the other decoders only (if any were asked for).
        quick = [f for f in functions if f is not _decode_opencv] or functions
        for step, processed, scale in _preprocessings(gray):
            for function in quick:
                add(function(np.ascontiguousarray(processed)), scale, step)
                if found:
                    return tuple(found)
    return tuple(found)
