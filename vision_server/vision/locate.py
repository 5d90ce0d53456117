"""Feature locate: template matching, round features (circles) and blobs, sub-pixel positions.

Positions are ``(u, v)`` full-image pixels (the ROI offset added back; the centre of the
top-left pixel is (0, 0)), angles in radians, best feature first.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any, Literal

import cv2
import numpy as np
from numpy.typing import NDArray

from vision_server.vision._checks import as_gray, check_positive, check_range, check_roi, crop
from vision_server.vision.errors import ParameterError, TemplateError

__all__ = ["Feature", "locate", "locate_blobs", "locate_circles", "locate_template"]

FloatArray = NDArray[np.float64]
Polarity = Literal["bright", "dark"]


@dataclass(frozen=True)
class Feature:
    """One located feature.

    Attributes
    ----------
    u, v : float
        Sub-pixel position in full-image pixels: the template's centre, the circle's centre
        or the blob's intensity-weighted centroid.
    angle : float
        Radians, counter-clockwise as displayed (v points down): the rotation applied to the
        template for the best match (OpenCV's ``getRotationMatrix2D`` sense), 0 for circles,
        the blob's principal-axis orientation in (-pi/2, pi/2].
    score : float
        Template: normalised cross-correlation (-1..1). Circle: fraction of the radial
        profiles whose edge lies on the fitted circle (0..1). Blob: circularity (0..1).
    radius : float or None
        Circle radius in pixels (circles only).
    area : float or None
        Blob area in pixels (anti-aliasing aware: edge pixels count by their coverage).
    """

    u: float
    v: float
    angle: float = 0.0
    score: float = 0.0
    radius: float | None = None
    area: float | None = None


# ---------------------------------------------------------------------------------------------
# template


def _parabola_peak(a: float, b: float, c: float) -> float:
    """Offset in (-0.5, 0.5) of the vertex of the parabola through (-1, a), (0, b), (1, c)."""
    denom = a - 2.0 * b + c
    if denom >= 0:
        return 0.0
    return float(np.clip(0.5 * (a - c) / denom, -0.5, 0.5))


def _rotated(template: NDArray[np.uint8], angle: float) -> tuple[NDArray[np.uint8], Any]:
    """The template rotated by ``angle`` (rad) about its centre, same size, and its valid mask."""
    if angle == 0.0:
        return template, None
    h, w = template.shape
    centre = ((w - 1) / 2.0, (h - 1) / 2.0)
    m = cv2.getRotationMatrix2D(centre, float(np.degrees(angle)), 1.0)
    rotated = cv2.warpAffine(template, m, (w, h), flags=cv2.INTER_LINEAR)
    mask = cv2.warpAffine(np.full((h, w), 255, np.uint8), m, (w, h), flags=cv2.INTER_NEAREST)
    mask = cv2.erode(mask, np.ones((3, 3), np.uint8))
    return np.asarray(rotated, np.uint8), mask


def locate_template(
    image: NDArray[np.uint8],
    template: NDArray[np.uint8] | None,
    *,
    roi: Sequence[float] | None = None,
    min_score: float = 0.7,
    max_count: int = 1,
    angle_range: tuple[float, float] = (0.0, 0.0),
    angle_step: float = np.deg2rad(5.0),
    min_distance: float | None = None,
) -> tuple[Feature, ...]:
    """Find ``template`` by normalised cross-correlation (``TM_CCOEFF_NORMED``).

    Parameters
    ----------
    image : (H, W) or (H, W, 3) uint8 ndarray
        Gray or BGR image.
    template : (h, w) or (h, w, 3) uint8 ndarray
        The pattern; its centre ``((w - 1) / 2, (h - 1) / 2)`` is the reported position.
    roi : [u, v, width, height], optional
        Where the template's whole extent must lie.
    min_score, max_count : float, int
        Keep at most ``max_count`` peaks scoring at least ``min_score``.
    angle_range, angle_step : (float, float), float
        Rotations of the template to try, radians (``(0, 0)``: no rotation search). The
        reported angle is refined by a parabola through the neighbouring angles' scores.
    min_distance : float, optional
        Non-maximum suppression distance in pixels (default: half the template's smaller side).

    Returns
    -------
    tuple of Feature
        Best first; the position is refined to sub-pixel by a parabola fit of the correlation
        peak along u and v.

    Raises
    ------
    TemplateError
        Missing, empty, non-uint8 template, or larger than the ROI.
    """
    gray = as_gray(image)
    if template is None:
        raise TemplateError("template is missing (the locate method 'template' needs one)")
    try:
        tmpl = as_gray(template, name="template")
    except ValueError as exc:
        raise TemplateError(f"template is unusable: {exc}") from exc
    box = check_roi(roi, gray.shape)
    region = np.ascontiguousarray(crop(gray, box), dtype=np.uint8)
    th, tw = tmpl.shape
    if th > region.shape[0] or tw > region.shape[1]:
        raise TemplateError(
            f"template ({tw}x{th}) is larger than the searched region "
            f"({region.shape[1]}x{region.shape[0]})"
        )
    if float(tmpl.std()) == 0.0:
        raise TemplateError("template is uniform (no contrast): correlation is undefined")
    if max_count < 1:
        raise ParameterError(f"max_count must be >= 1, got {max_count}")
    a0, a1 = check_range(*angle_range, "angle_range")
    if a1 > a0:
        step = check_positive(angle_step, "angle_step")
        angles = np.arange(a0, a1 + 1e-9, step)
    else:
        angles = np.array([a0])
    maps = []
    for angle in angles:
        rotated, mask = _rotated(tmpl, float(angle))
        result = cv2.matchTemplate(region, rotated, cv2.TM_CCOEFF_NORMED, mask=mask)
        maps.append(np.nan_to_num(np.asarray(result, np.float64), nan=-1.0, posinf=-1.0))
    stack = np.stack(maps)  # (A, H', W')
    best_angle = np.argmax(stack, axis=0)
    score = np.max(stack, axis=0)
    radius = float(min_distance) if min_distance is not None else 0.5 * min(th, tw)
    work = score.copy()
    features: list[Feature] = []
    hh, ww = work.shape
    yy, xx = np.mgrid[0:hh, 0:ww]
    while len(features) < max_count:
        idx = int(np.argmax(work))
        y, x = divmod(idx, ww)
        peak = float(work[y, x])
        if peak < min_score:
            break
        k = int(best_angle[y, x])
        m = stack[k]
        dx = _parabola_peak(m[y, x - 1], m[y, x], m[y, x + 1]) if 0 < x < ww - 1 else 0.0
        dy = _parabola_peak(m[y - 1, x], m[y, x], m[y + 1, x]) if 0 < y < hh - 1 else 0.0
        angle = float(angles[k])
        if 0 < k < len(angles) - 1:
            da = _parabola_peak(stack[k - 1, y, x], stack[k, y, x], stack[k + 1, y, x])
            angle += da * float(angles[1] - angles[0])
        features.append(
            Feature(
                u=box[0] + x + dx + (tw - 1) / 2.0,
                v=box[1] + y + dy + (th - 1) / 2.0,
                angle=angle,
                score=peak,
            )
        )
        work[(xx - x) ** 2 + (yy - y) ** 2 <= radius * radius] = -np.inf
    return tuple(features)


# ---------------------------------------------------------------------------------------------
# circles


def _fit_circle(points: FloatArray) -> tuple[float, float, float]:
    """Algebraic (Kasa) least-squares circle ``(u, v, r)`` through ``points`` (N, 2)."""
    x, y = points[:, 0], points[:, 1]
    a = np.column_stack([x, y, np.ones_like(x)])
    b = x * x + y * y
    (p, q, c), *_ = np.linalg.lstsq(a, b, rcond=None)
    u, v = p / 2.0, q / 2.0
    return float(u), float(v), float(np.sqrt(max(c + u * u + v * v, 0.0)))


def _refine_circle(
    gray: FloatArray, u: float, v: float, r: float, rays: int = 90
) -> tuple[float, float, float, float] | None:
    """Refine a circle by sub-pixel edges along radial profiles; ``(u, v, r, inlier_frac)``."""
    thetas = np.linspace(0.0, 2 * np.pi, rays, endpoint=False)
    dirs = np.column_stack([np.cos(thetas), np.sin(thetas)])
    frac = 0.0
    for half in (max(3.0, 0.25 * r), 2.0):
        step = 0.1
        offsets = np.arange(-half, half + step / 2, step)
        radii = np.maximum(r + offsets, 0.5)
        pu = (u + dirs[:, 0:1] * radii[None, :]).astype(np.float32)
        pv = (v + dirs[:, 1:2] * radii[None, :]).astype(np.float32)
        prof = cv2.remap(
            gray.astype(np.float32), pu, pv, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE
        ).astype(np.float64)
        inner = np.median(prof[:, : len(offsets) // 4])
        outer = np.median(prof[:, -len(offsets) // 4 :])
        if abs(inner - outer) < 5.0:
            return None
        # Edge = where the profile crosses the mid level between inside and outside: unbiased
        # for a symmetric blur, and robust to noise when taken on the smoothed profile.
        smooth = cv2.blur(prof, (5, 1), borderType=cv2.BORDER_REPLICATE).astype(np.float64)
        mid = 0.5 * (inner + outer)
        sign = np.sign(smooth[:, 2:-2] - mid) * np.sign(inner - outer)
        pts = []
        for i in range(rays):
            crossings = np.flatnonzero((sign[i, :-1] > 0) & (sign[i, 1:] <= 0))
            if crossings.size == 0:
                continue
            j = int(crossings[np.argmin(np.abs(offsets[crossings + 2]))]) + 2
            s0, s1 = smooth[i, j] - mid, smooth[i, j + 1] - mid
            t = s0 / (s0 - s1) if s0 != s1 else 0.5
            rad = radii[j] + t * step
            pts.append((u + dirs[i, 0] * rad, v + dirs[i, 1] * rad))
        if len(pts) < 8:
            return None
        p = np.array(pts)
        keep = np.ones(len(p), bool)
        for _ in range(3):
            cu, cv_, cr = _fit_circle(p[keep])
            res = np.abs(np.hypot(p[:, 0] - cu, p[:, 1] - cv_) - cr)
            tol = max(0.3, 3.0 * 1.4826 * float(np.median(res[keep])))
            keep = res <= tol
            if keep.sum() < 8:
                return None
        u, v, r = _fit_circle(p[keep])
        frac = float(keep.sum()) / rays
    return u, v, r, frac


def locate_circles(
    image: NDArray[np.uint8],
    *,
    roi: Sequence[float] | None = None,
    radius_range: tuple[float, float] = (5.0, 100.0),
    min_score: float = 0.5,
    max_count: int = 1,
    canny_high: float = 100.0,
    accumulator_threshold: float = 20.0,
) -> tuple[Feature, ...]:
    """Find round features (e.g. a rotor cap's top, bright or dark) with sub-pixel centres.

    Candidates come from ``cv2.HoughCircles`` (gradient method); each is refined by locating
    the edge on 90 radial profiles (where the smoothed profile crosses the mid level between
    inside and outside, linear interpolation at 0.1 px steps) and fitting a circle to the edge
    points with outlier rejection.

    Parameters
    ----------
    radius_range : (float, float)
        Least and greatest radius in pixels.
    min_score : float
        Least fraction of radial profiles whose edge lies on the circle.
    max_count : int
        At most this many circles.
    canny_high, accumulator_threshold : float
        ``param1`` and ``param2`` of ``cv2.HoughCircles``.
    """
    gray = as_gray(image)
    box = check_roi(roi, gray.shape)
    region = np.ascontiguousarray(crop(gray, box))
    r0, r1 = check_range(*radius_range, "radius_range")
    if r0 <= 0:
        raise ParameterError(f"radius_range must be positive, got {radius_range}")
    if max_count < 1:
        raise ParameterError(f"max_count must be >= 1, got {max_count}")
    blurred = cv2.GaussianBlur(region, (5, 5), 1.2)
    found = cv2.HoughCircles(
        blurred,
        cv2.HOUGH_GRADIENT,
        dp=1.0,
        minDist=max(r0, 4.0),
        param1=canny_high,
        param2=accumulator_threshold,
        minRadius=int(np.floor(r0)),
        maxRadius=int(np.ceil(r1)),
    )
    if found is None:
        return ()
    work = region.astype(np.float64)
    features: list[Feature] = []
    for cu, cv_, cr in np.asarray(found, np.float64).reshape(-1, 3)[: 4 * max_count + 8]:
        refined = _refine_circle(work, float(cu), float(cv_), float(cr))
        if refined is None:
            continue
        u, v, r, frac = refined
        if not (r0 - 1.0 <= r <= r1 + 1.0) or frac < min_score:
            continue
        if any(np.hypot(f.u - box[0] - u, f.v - box[1] - v) < max(r0, 0.5 * r) for f in features):
            continue
        features.append(Feature(u=box[0] + u, v=box[1] + v, angle=0.0, score=frac, radius=r))
    features.sort(key=lambda f: -f.score)
    return tuple(features[:max_count])


# ---------------------------------------------------------------------------------------------
# blobs


def _threshold(region: NDArray[np.uint8], threshold: float | None) -> float:
    if threshold is None:
        t, _ = cv2.threshold(region, 0, 255, cv2.THRESH_BINARY | cv2.THRESH_OTSU)
        return float(t)
    t = float(threshold)
    if not 0 <= t <= 255:
        raise ParameterError(f"threshold must be in 0..255 or None (Otsu), got {threshold!r}")
    return t


def locate_blobs(
    image: NDArray[np.uint8],
    *,
    roi: Sequence[float] | None = None,
    threshold: float | None = None,
    polarity: Polarity = "bright",
    area_range: tuple[float, float] = (10.0, float("inf")),
    min_circularity: float = 0.0,
    max_count: int = 100,
) -> tuple[Feature, ...]:
    """Find blobs: connected regions above (``bright``) or below (``dark``) a threshold.

    Parameters
    ----------
    threshold : float or None
        Grey level 0..255; None = Otsu's threshold of the ROI.
    polarity : {"bright", "dark"}
        Whether the blobs are brighter or darker than the threshold.
    area_range : (float, float)
        Accepted areas in pixels.
    min_circularity : float
        Least ``4 pi area / perimeter**2`` (1 for a disc).
    max_count : int
        At most this many blobs, largest first.

    Returns
    -------
    tuple of Feature
        Centroid from intensity-weighted moments over the blob grown by 2 pixels, the weights
        being each pixel's coverage ``(I - background) / (foreground - background)`` clipped to
        0..1 (so anti-aliased edge pixels count by their share); ``score`` = circularity,
        ``area`` = the summed coverage, ``angle`` = principal axis orientation.
    """
    gray = as_gray(image)
    box = check_roi(roi, gray.shape)
    region = np.ascontiguousarray(crop(gray, box))
    if polarity not in ("bright", "dark"):
        raise ParameterError(f"polarity must be 'bright' or 'dark', got {polarity!r}")
    a0, a1 = float(area_range[0]), float(area_range[1])
    if not a0 <= a1:
        raise ParameterError(f"area_range must have min <= max, got {area_range}")
    t = _threshold(region, threshold)
    work = region.astype(np.float64)
    if polarity == "dark":
        work = 255.0 - work
        t = 255.0 - t
    binary = (work > t).astype(np.uint8)
    fg_vals, bg_vals = work[binary > 0], work[binary == 0]
    if fg_vals.size == 0 or bg_vals.size == 0:
        return ()
    fg, bg = float(np.median(fg_vals)), float(np.median(bg_vals))
    coverage = np.clip((work - bg) / max(fg - bg, 1e-6), 0.0, 1.0)
    count, labels, stats, _ = cv2.connectedComponentsWithStats(binary, connectivity=8)
    grown_kernel = np.ones((5, 5), np.uint8)
    features: list[Feature] = []
    for label in range(1, count):
        x, y, w, h, area_px = (int(s) for s in stats[label])
        x0, y0 = max(x - 3, 0), max(y - 3, 0)
        x1, y1 = min(x + w + 3, region.shape[1]), min(y + h + 3, region.shape[0])
        mask = (labels[y0:y1, x0:x1] == label).astype(np.uint8)
        contours, _ = cv2.findContours(mask, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)
        perimeter = sum(cv2.arcLength(c, True) for c in contours)
        grown = cv2.dilate(mask, grown_kernel) > 0
        weights = coverage[y0:y1, x0:x1] * grown
        area = float(weights.sum())
        if not a0 <= area <= a1 or area <= 0:
            continue
        circularity = float(min(1.0, 4 * np.pi * area / perimeter**2)) if perimeter > 0 else 0.0
        if circularity < min_circularity:
            continue
        ys, xs = np.mgrid[y0:y1, x0:x1]
        cu = float((weights * xs).sum() / area)
        cv_ = float((weights * ys).sum() / area)
        mu20 = float((weights * (xs - cu) ** 2).sum() / area)
        mu02 = float((weights * (ys - cv_) ** 2).sum() / area)
        mu11 = float((weights * (xs - cu) * (ys - cv_)).sum() / area)
        angle = -0.5 * float(np.arctan2(2 * mu11, mu20 - mu02))  # v down: negate
        del area_px
        features.append(
            Feature(u=box[0] + cu, v=box[1] + cv_, angle=angle, score=circularity, area=area)
        )
    features.sort(key=lambda f: -(f.area or 0.0))
    return tuple(features[:max_count])


# ---------------------------------------------------------------------------------------------
# dispatcher


def locate(
    image: NDArray[np.uint8],
    *,
    method: Literal["template", "circle", "blob"],
    **options: Any,
) -> tuple[Feature, ...]:
    """Locate features with ``method`` (``template``, ``circle`` or ``blob``).

    ``options`` are the keyword arguments of :func:`locate_template` (including ``template``),
    :func:`locate_circles` or :func:`locate_blobs`.
    """
    if method == "template":
        options = dict(options)
        template = options.pop("template", None)
        return locate_template(image, template, **options)
    if method == "circle":
        return locate_circles(image, **options)
    if method == "blob":
        return locate_blobs(image, **options)
    raise ParameterError(f"method must be 'template', 'circle' or 'blob', got {method!r}")
