"""A circle's centre as the first moment of its intensity: the reading that blur cannot move.

Blurring with a kernel whose own centroid is at zero (a Gaussian, a defocus disc) preserves the
first moment of an isolated blob exactly: ``sum(x * (k * I)) / sum(k * I) == sum(x * I) /
sum(I)``. So the centroid of the background-subtracted intensity, taken over a window large
enough to hold all of the blurred blob, is the same number on the sharp and the blurred image,
whatever grey-level structure the part has near its rim (a lit rim, relief). An edge reading is
local and has no such guarantee. The price: the centroid is that of the intensity, not of the
outline, so a part that is brighter on one side (a lit rim) reads off its geometric centre by
the same amount, sharp or blurred.

Pixels are ``(u, v)`` = (column, row) of the image given, the centre of the top-left pixel at
``(0.0, 0.0)``.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from typing import Literal

import cv2
import numpy as np
from numpy.typing import NDArray

from .edge_width import edge_sigma

__all__ = ["COMMON_SCALE_PX", "WINDOW_SIGMAS", "moment_centre"]

FloatArray = NDArray[np.float64]
Circle = tuple[float, float, float]
PlaneFn = Callable[[FloatArray, FloatArray], FloatArray]

COMMON_SCALE_PX = 4.5
"""Blur (Gaussian sigma, px) to which every part's surroundings are brought before its moments
are taken: the most blur the centre is meant to be consistent through (4 px) and a margin for
the measured sigma's error. Moments alone would not need it for an isolated part; with a
neighbour a few px away, or background texture that the window's edge cuts, they do: the same
scale makes the sharp and the blurred image the same image. The scale reached is measured
again on the smoothed image and corrected (:func:`_at_common_scale`): the blur measured on the
input is not exact enough for that."""
WINDOW_SIGMAS = 2.0
"""How far beyond the part's radius the window reaches, in sigmas of the common scale (plus
``_WINDOW_PAD``). At the common scale the sharp and the blurred image are the same image, so
cutting the faint last 2 % of the edge's spread is the same cut in both; a narrower window keeps
clear of the image's border and of neighbours (coins at sigma 4: worst 0.5 px from the sharp
answer with 2 sigmas, 0.9 px with 3)."""
_WINDOW_PAD = 2.0  # px
_RING_PX = 4.0  # px: width of the background ring outside the window
_TAPER_PX = 5.0  # px: width of every window's smooth edge
_BORDER_PX = 0.0  # px: how far the window's tapered edge keeps inside the image's border
_SCALE_ROUNDS = 3  # re-measurements of the blur at the common scale
_SCALE_TOLERANCE = 0.02  # px of sigma: close enough to the common scale
_SCALE_REACH = 3.0  # sigmas either side of the edge searched when measuring it
_SCALE_RAYS = 32  # rays the blur is measured on at the common scale
_ITERATIONS = 4
_MIN_STEP = 2.0  # grey levels: below it a pixel's coverage is mostly noise
_MAX_GROWTH = 1.45
"""Most the part's equivalent radius (from its area) may differ from the edge fit's, as a factor:
an edge fit can settle on a ring of relief inside a coin (19 px on a 26 px coin, once in 240
coin images), which the moments then read whole; beyond it the light is not this part's."""
_MAX_DRIFT = 0.5  # of the radius: a centroid further from the edge's centre is not this part


def moment_centre(
    image: FloatArray,
    circle: Circle,
    *,
    blur_sigma_px: float,
    polarity: Literal["bright", "dark"] = "bright",
    others: Sequence[Circle] = (),
    scale_px: float = COMMON_SCALE_PX,
) -> tuple[float, float, float] | str:
    """The part's centroid and equivalent radius ``(u, v, r)`` in px, or why not (str).

    Parameters
    ----------
    image : (H, W) ndarray of float
        Gray levels.
    circle : (u, v, r)
        The part as an edge reading found it (px); ``r`` sets the window, ``(u, v)`` its first
        placement.
    blur_sigma_px : float
        The blur already in the image around the part, as a Gaussian sigma (px).
    polarity : {'bright', 'dark'}
        A part brighter (default) or darker than its surroundings.
    others : sequence of (u, v, r)
        Neighbouring parts (px). A pixel counts for the part whose edge is nearer, and the
        background ring keeps clear of every neighbour's window.
    scale_px : float
        The common blur (sigma, px) the surroundings are brought to first: smoothed by
        ``sqrt(scale² - blur_sigma²)`` (nothing if the blur is already wider).

    Notes
    -----
    The window is the disc of radius ``r + WINDOW_SIGMAS * scale + 2`` px, re-centred on each
    new centroid. The background is a plane fitted (least squares, refitted once without
    outliers) to a ring ``_RING_PX`` wide just outside it, so a lighting gradient across the
    part does not move the centroid. Weights are ``I - background`` unclipped (clipping is not
    linear and would lose the blur invariance); dark parts use ``background - I``. Every edge
    of the window (its disc, the line shared with a neighbour, the image's border) is a smooth
    ``_TAPER_PX`` wide ramp that moves with the centre, so the answer follows a sub-pixel move
    of the image continuously. Near the image's border the window is cut alike on both sides
    of the centre (:func:`_border_cut`).
    """
    u, v, r = circle
    scale = max(scale_px, blur_sigma_px)
    extra = math.sqrt(max(scale**2 - max(blur_sigma_px, 0.0) ** 2, 0.0))
    pad = WINDOW_SIGMAS * scale + _WINDOW_PAD
    height, width = image.shape
    # One smoothed patch serves every iteration: the window may drift by _MAX_DRIFT * r and
    # grow with the radius up to _MAX_GROWTH * r.
    margin = (_MAX_GROWTH + _MAX_DRIFT) * r + pad + _RING_PX + 3.0 * extra + 2.0
    bx0, by0 = max(int(u - margin), 0), max(int(v - margin), 0)
    bx1, by1 = min(int(u + margin) + 2, width), min(int(v + margin) + 2, height)
    patch = _at_common_scale(
        np.ascontiguousarray(image[by0:by1, bx0:bx1], np.float64),
        (u - bx0, v - by0, r),
        extra=extra,
        target=scale if scale_px >= blur_sigma_px else None,
        polarity=polarity,
    )
    sign = 1.0 if polarity == "bright" else -1.0
    for _ in range(_ITERATIONS):
        reach = r + pad
        outer = reach + _RING_PX
        x0, y0 = (
            max(int(math.floor(u - outer - _TAPER_PX)), bx0),
            max(int(math.floor(v - outer - _TAPER_PX)), by0),
        )
        x1 = min(int(math.ceil(u + outer + _TAPER_PX)) + 1, bx1)
        y1 = min(int(math.ceil(v + outer + _TAPER_PX)) + 1, by1)
        ys, xs = np.mgrid[y0:y1, x0:x1].astype(np.float64)
        values = patch[y0 - by0 : y1 - by0, x0 - bx0 : x1 - bx0]
        rho = np.hypot(xs - u, ys - v)
        # Every mask is a smooth weight that moves with (u, v): a hard one gains or loses a
        # whole column of pixels as the image moves by a fraction of one, which moved the
        # centroid by up to 0.2 px on the coins with no blur at all.
        ours = _taper(reach - rho)
        clear = _taper(rho - reach) * _taper(outer - rho)
        for ou, ov, orad in others:
            if math.hypot(ou - u, ov - v) - orad > outer + pad + _TAPER_PX:
                continue  # too far to share a pixel of this window or its ring
            theirs = np.hypot(xs - ou, ys - ov) - orad
            # A pixel belongs to the part whose edge is nearer (the bisector of the gap between
            # two parts): at the common scale as much of a like neighbour's light crosses that
            # line as of ours. Tapered both ways, so the two parts' weights sum to one.
            ours *= _taper(theirs - (rho - r))
            clear *= _taper(theirs - (reach - r))
        cut = _border_cut(xs, ys, (u, v), (width, height), reach)
        ring = clear > 0.5
        if ring.sum() < 12:
            return "neighbours hide the background ring around the part"
        background = _plane(xs[ring], ys[ring], values[ring])
        inside = ours > 0.0
        core = (ours > 0.5) & (rho <= max(r - 2.0 * scale, 0.5 * r))
        level = float(np.median(values[core])) if core.any() else math.nan
        behind = background(xs[inside], ys[inside])
        # An opaque part hides the background behind it: with the background sloping, the
        # plain difference I - background would weigh the part's darker-background side more
        # (0.14 px on a 44 px disc over a 20-grey ramp). Its coverage (0..1) weighs it evenly.
        step = sign * (level - behind)
        if not (np.isfinite(step).all() and float(step.min()) >= _MIN_STEP):
            return (
                f"the part is not {_MIN_STEP:g} grey levels {'brighter' if sign > 0 else 'darker'}"
                " than its background everywhere behind it"
            )
        coverage = ours[inside] * sign * (values[inside] - behind) / step
        weights = cut[inside] * coverage
        mass = float(weights.sum())
        if not mass > 0:
            return "no light above the background in the moment window"
        u_new = float((weights * xs[inside]).sum()) / mass
        v_new = float((weights * ys[inside]).sum()) / mass
        if math.hypot(u_new - circle[0], v_new - circle[1]) > _MAX_DRIFT * r:
            return "the intensity centroid lies more than half a radius from the edge's centre"
        # The window follows the part's own size: its coverage's area, which blur keeps (the
        # edge fit's radius shrinks with blur, by up to 3 px on a worn coin at sigma 4). Taken
        # without the border's mirrored cut, which would shrink it: only the image's border
        # cuts it then, in the blurred edge's faint outer tail at most.
        r_new = math.sqrt(max(float(coverage.sum()), 0.0) / math.pi)
        if not circle[2] / _MAX_GROWTH <= r_new <= circle[2] * _MAX_GROWTH:
            return (
                f"the part's light covers a disc of radius {r_new:.1f} px, not about the edge's "
                f"{circle[2]:.1f} px"
            )
        settled = math.hypot(u_new - u, v_new - v) + abs(r_new - r) < 0.005
        u, v, r = u_new, v_new, r_new
        if settled:
            break
    return u, v, r


def _at_common_scale(
    patch: FloatArray,
    circle: Circle,
    *,
    extra: float,
    target: float | None,
    polarity: Literal["bright", "dark"],
) -> FloatArray:
    """``patch`` smoothed by ``extra`` px, then by more or less until its edge around
    ``circle`` (px, in the patch) measures ``target`` px (None: ``extra`` as given).

    The blur measured before (:func:`.edge_width.edge_sigma`) is floored at 1 px on a sharp
    image and reads 0.1..0.2 px under the true one on a blurred coin, so the sharp and the
    blurred image were brought to scales 0.2..0.3 px apart: enough, with a neighbour 8 px away,
    to move a coin's centre by 0.1 px at sigma 4. Measured again at the common scale, the same
    part reads alike whatever the blur it came with, so the two end at one scale.
    """
    smoothed = _smoothed(patch, extra)
    if target is None:
        return smoothed
    reach = _SCALE_REACH * target
    for _ in range(_SCALE_ROUNDS):
        seen = edge_sigma(
            smoothed,
            circle[:2],
            circle[2],
            polarity=polarity,
            rays=_SCALE_RAYS,
            reach=reach,
            interpolate=True,
        )
        if seen is None or abs(seen - target) < _SCALE_TOLERANCE:
            break
        extra = math.sqrt(max(extra**2 + target**2 - seen**2, 0.0))
        smoothed = _smoothed(patch, extra)
    return smoothed


def _smoothed(patch: FloatArray, sigma: float) -> FloatArray:
    """``patch`` blurred by a Gaussian of ``sigma`` px (as it is below 0.05 px).

    OpenCV's default border (mirrored about the edge pixel), so that an image blurred by
    OpenCV, as the bench's are, and this blur compose into one."""
    if sigma <= 0.05:
        return patch
    blurred = cv2.GaussianBlur(patch, (0, 0), sigma, borderType=cv2.BORDER_REFLECT_101)
    return np.asarray(blurred, np.float64)


def _taper(distance: FloatArray) -> FloatArray:
    """Weight 0..1 rising smoothly (smoothstep, ``_TAPER_PX`` wide) as ``distance`` (px)
    goes from ``-_TAPER_PX / 2`` to ``+_TAPER_PX / 2``: 0.5 on the line itself."""
    t = np.clip(distance * (1.0 / _TAPER_PX) + 0.5, 0.0, 1.0)
    return np.asarray(t * t * (3.0 - 2.0 * t), np.float64)


def _border_cut(
    xs: FloatArray,
    ys: FloatArray,
    centre: tuple[float, float],
    size: tuple[int, int],
    reach: float,
) -> FloatArray:
    """Weights that keep the window clear of the image's border, cut alike on both sides of
    the centre (mirrored about it): light lost beyond one border is then given up on the
    other side too, so a part symmetric about its centre still reads it; all ones when the
    window does not come near the border."""
    u, v = centre
    width, height = size
    weights = np.ones(xs.shape, np.float64)
    for offset, low, high in ((xs - u, u, width - 1 - u), (ys - v, v, height - 1 - v)):
        half = min(low, high) - _BORDER_PX - _TAPER_PX / 2
        if half < reach + _TAPER_PX / 2:
            weights *= _taper(half - np.abs(offset))
    return weights


def _plane(xs: FloatArray, ys: FloatArray, values: FloatArray) -> PlaneFn:
    """Least-squares plane ``a + b x + c y`` through the ring's gray levels, refitted once
    without the points more than 3 robust sigmas off (a neighbour's halo, a scratch)."""
    design = np.column_stack([np.ones_like(xs), xs, ys])
    coef, *_ = np.linalg.lstsq(design, values, rcond=None)
    residual = values - design @ coef
    spread = 1.4826 * float(np.median(np.abs(residual - np.median(residual))))
    keep = np.abs(residual) <= max(3.0 * spread, 1.0)
    if keep.sum() >= 12:
        coef, *_ = np.linalg.lstsq(design[keep], values[keep], rcond=None)
    a, b, c = (float(x) for x in coef)

    def at(x: FloatArray, y: FloatArray) -> FloatArray:
        return np.asarray(a + b * x + c * y, np.float64)

    return at
