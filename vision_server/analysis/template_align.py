"""Sub-pixel pose of a located template by robust image alignment, which part occlusion does not
pull.

Normalised cross-correlation (NCC) finds a template well, but where something hides part of it
the NCC peak moves: a pose that puts less of the template over the occluder scores higher, so a
quarter hidden moves the peak by 0.5..1.5 px and, with a scale search, drags the scale to the
end of its range (rendered parts, tests/vision_server/analysis/test_locate_template_pose.py).
Here the pose found by NCC is refined by Gauss-Newton alignment of the template to the image
(position, and angle and scale where they are searched, plus the image's gain and offset)
in which pixels that disagree with the template by much more than the others, over an area
(:func:`_hidden`: the occluder), get weight 0 and stop pulling, wherever they are; everything
else is plain least squares.

Coordinates: ``(u, v)`` is where the template's centre lies, in the pixels of the image given;
``angle`` (rad, +u towards +v) and ``scale`` (image size / template size) map a template point
``q`` (px from its centre) to ``(u, v) + scale * R(angle) q``.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray

__all__ = ["Alignment", "align_template"]

FloatArray = NDArray[np.float64]

OUTLIER = 4.0
"""A pixel disagrees with the template when its residual exceeds this many robust standard
deviations of all residuals."""
HIDDEN_WIDTH = 5
"""Disagreeing pixels count as hidden only where they fill a disc this wide (template px): an
occluder hides an area, while a thin band of disagreement along the part's edges is the part's
own shape differing from the template (a side wall seen in perspective, wear, a resampled
edge) and must keep pulling as in plain least squares, or the fit slides to match one edge."""
NOISE_FLOOR = 1.0
"""Smallest robust residual spread assumed (grey levels): a synthetic, noiseless image must not
make every pixel an outlier."""
SETTLED = 0.003
"""A step under this (px, at the template's rim) ends the alignment."""


@dataclass(frozen=True)
class Alignment:
    """A template's refined pose and how well the image agrees with it.

    ``score``: NCC (-1..1) of the template with the image resampled at this pose over the whole
    correlated area (hidden pixels included, so occlusion lowers it). ``visible``: the share
    (0..1) of the template's pixels not found hidden (:func:`_hidden`): about the share not
    covered by an occluder (hidden pixels whose grey happens to match the template count as
    visible). ``spread``: the robust standard deviation (grey levels) of the residuals of the
    pixels not hidden: about the camera noise at the right pose, much more at a wrong one.
    """

    u: float
    v: float
    angle: float
    scale: float
    score: float
    visible: float
    spread: float


def _points(
    template: NDArray[Any], disc: bool
) -> tuple[FloatArray, FloatArray, FloatArray, NDArray[np.bool_]]:
    """Template pixels correlated (its inscribed disc, or all), as offsets from its centre, their
    grey levels, and the mask (h, w) that picks them."""
    h, w = template.shape
    ys, xs = np.mgrid[0:h, 0:w].astype(np.float64)
    qx, qy = xs - (w - 1) / 2.0, ys - (h - 1) / 2.0
    keep = np.ones((h, w), bool)
    if disc:
        r = (min(h, w) - 1) / 2.0
        keep = qx * qx + qy * qy <= r * r
    return qx[keep], qy[keep], template[keep].astype(np.float64), keep


def _robust_levels(template: FloatArray, image: FloatArray) -> tuple[float, float]:
    """Gain and offset with ``image ~ gain * template + offset``, fitted on the pixels that
    agree (least squares, then again without those beyond 2.5 robust standard deviations, three
    times): a plain fit over an occluder shrinks the gain, and every pixel then disagrees."""
    use = np.ones(template.shape, bool)
    gain, offset = 1.0, 0.0
    for _ in range(4):
        if use.sum() < 3 or float(np.ptp(template[use])) == 0.0:
            break
        gain, offset = (float(x) for x in np.polyfit(template[use], image[use], 1))
        residual = np.abs(image - (gain * template + offset))
        spread = max(1.4826 * float(np.median(residual)), NOISE_FLOOR)
        use = residual <= 2.5 * spread
    return gain, offset


def _hidden(outlier: NDArray[np.bool_], keep: NDArray[np.bool_]) -> NDArray[np.bool_]:
    """The outliers (per template point) in regions that contain an area at least
    ``HIDDEN_WIDTH`` px wide (a morphological opening of the outlier map in template pixels,
    then the connected outlier regions it touches)."""
    grid = np.zeros(keep.shape, np.uint8)
    grid[keep] = outlier
    disc = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (HIDDEN_WIDTH, HIDDEN_WIDTH))
    opened = cv2.morphologyEx(grid, cv2.MORPH_OPEN, disc)
    # The whole of every outlier region that holds such an area: the tips and rim of an
    # occluder are thinner than the disc but hidden all the same.
    count, labels = cv2.connectedComponents(grid, connectivity=8)
    wide = np.zeros(count, bool)
    wide[np.unique(labels[opened > 0])] = True
    wide[0] = False
    return np.asarray(wide[labels[keep]], dtype=bool)


SAMPLE_ROW = 4096
"""Points sampled per row of the maps given to ``cv2.remap``, which takes maps of fewer than
32767 columns: a template of more than 181 x 181 pixels has more points than one row holds."""


def _sample(
    image: NDArray[Any],
    px: FloatArray,
    py: FloatArray,
    *,
    border: int,
    value: tuple[float, ...] = (0.0, 0.0, 0.0, 0.0),
) -> NDArray[np.float32]:
    """``image`` (one or more channels) read bilinearly at the points ``(px, py)`` (pixels),
    one row per point in their order: ``(n,)`` or ``(n, channels)``."""
    n = int(px.size)
    rows = max(1, -(-n // SAMPLE_ROW))
    width = min(n, SAMPLE_ROW) if n else 1
    mx = np.zeros(rows * width, np.float32)
    my = np.zeros(rows * width, np.float32)
    mx[:n] = px.ravel()
    my[:n] = py.ravel()
    out = cv2.remap(
        image,
        mx.reshape(rows, width),
        my.reshape(rows, width),
        cv2.INTER_LINEAR,
        borderMode=border,
        borderValue=value,
    )
    channels = 1 if out.ndim == 2 else out.shape[2]
    flat = out.reshape(rows * width, channels)[:n]
    return np.asarray(flat if channels > 1 else flat.ravel(), np.float32)


@dataclass
class _State:
    """The pose being aligned, in the patch's pixels, and the image's gain and offset."""

    u: float
    v: float
    angle: float
    scale: float
    gain: float = 1.0
    offset: float = 0.0
    hidden: NDArray[np.bool_] | None = None
    spread: float = np.inf


def _gauss_newton(
    patch: NDArray[np.float32],
    points: tuple[FloatArray, FloatArray, FloatArray, NDArray[np.bool_]],
    state: _State,
    *,
    free: list[bool],
    origin: tuple[float, float],
    max_move: float,
    iterations: int,
) -> _State | None:
    """Align template points to ``patch`` from ``state``; the settled state, or None."""
    qx, qy, tv, keep = points
    grad_x = cv2.Sobel(patch, cv2.CV_32F, 1, 0, ksize=3, scale=1.0 / 8.0)
    grad_y = cv2.Sobel(patch, cv2.CV_32F, 0, 1, ksize=3, scale=1.0 / 8.0)
    stack = cv2.merge([patch, grad_x, grad_y])
    u, v, angle, scale = state.u, state.v, state.angle, state.scale
    gain, offset = state.gain, state.offset
    rim = 0.5 * float(np.hypot(np.ptp(qx), np.ptp(qy))) / np.sqrt(2.0)
    for it in range(iterations):
        c, s = np.cos(angle), np.sin(angle)
        rx, ry = c * qx - s * qy, s * qx + c * qy  # R q
        px, py = u + scale * rx, v + scale * ry
        sampled = _sample(
            stack, px, py, border=cv2.BORDER_CONSTANT, value=(np.nan, np.nan, np.nan, 0.0)
        ).reshape(-1, 3)
        sampled = np.nan_to_num(sampled)
        inside = (px >= 0) & (py >= 0) & (px <= patch.shape[1] - 1) & (py <= patch.shape[0] - 1)
        if inside.mean() < 0.9:
            return None  # most of the template off the image: not ours to refine
        grey, gx, gy = (sampled[:, k].astype(np.float64) for k in range(3))
        if it == 0 and state.hidden is None:
            gain, offset = _robust_levels(tv[inside], grey[inside])
        residual = np.where(inside, grey - (gain * tv + offset), 0.0)
        spread = max(1.4826 * float(np.median(np.abs(residual[inside]))), NOISE_FLOOR)
        hidden = _hidden(np.abs(residual) > OUTLIER * spread, keep)
        weights = np.where(inside & ~hidden, 1.0, 0.0)
        columns = np.stack(
            [
                gx,
                gy,
                scale * (gx * -ry + gy * rx),  # d(pixel)/d(angle) = scale * R' q
                gx * rx + gy * ry,  # d(pixel)/d(scale) = R q
                -tv,
                -np.ones_like(tv),
            ],
            axis=1,
        )[:, free]
        jw = columns * weights[:, None]
        try:
            step = np.linalg.solve(jw.T @ columns, -(jw.T @ residual))
        except np.linalg.LinAlgError:
            return None
        full = np.zeros(6)
        full[free] = step
        if not (np.all(np.isfinite(full)) and scale + full[3] > 0):
            return None
        u, v, angle, scale = u + full[0], v + full[1], angle + full[2], scale + full[3]
        gain, offset = gain + full[4], offset + full[5]
        if np.hypot(u - origin[0], v - origin[1]) > max_move:
            return None
        # Re-weighting makes the last steps shrink geometrically rather than quadratically:
        # stop when a step moves the template's rim by under SETTLED px.
        moved = max(abs(full[0]), abs(full[1])) + rim * scale * (abs(full[2]) + abs(full[3]))
        if it >= 1 and moved < SETTLED:
            agree = residual[inside & ~hidden]
            spread = 1.4826 * float(np.median(np.abs(agree))) if len(agree) else np.inf
            return _State(u, v, angle, scale, gain, offset, hidden, spread)
    return None


def align_template(
    image: NDArray[np.uint8],
    template: NDArray[np.uint8],
    start: tuple[float, float, float, float],
    *,
    disc: bool,
    fit_angle: bool,
    fit_scale: bool,
    max_move: float,
    iterations: int = 40,
) -> Alignment | None:
    """Refine a template's pose ``start`` = ``(u, v, angle, scale)`` in ``image``.

    From a start far off (correlation under occlusion can put the scale 0.15 off) this may
    settle on a wrong pose that explains the occluder as texture; such a pose leaves a large
    ``spread``: the caller tries several starts and keeps the one with the smallest.

    Parameters
    ----------
    image, template : ndarray
        ``uint8`` gray ``(H, W)`` and ``(h, w)``.
    start : (float, float, float, float)
        The pose found by correlation (module docstring for the frame and units).
    disc : bool
        Align only the template's inscribed disc (as a rotation search correlates it).
    fit_angle, fit_scale : bool
        Whether the angle and scale are refined; else they stay as in ``start``.
    max_move : float
        Farthest (px) the refined centre may lie from ``start``'s.
    iterations : int
        Most Gauss-Newton steps per pass.

    Returns
    -------
    Alignment or None
        None when the alignment leaves the image, does not settle, or moves more than
        ``max_move`` px (the caller keeps the correlation's pose).
    """
    points = _points(template, disc)
    u, v, angle, scale = (float(x) for x in start)
    reach = 0.5 * float(np.hypot(*template.shape)) * scale * 1.2 + max_move + 4.0
    height, width = image.shape
    x0, y0 = max(int(u - reach), 0), max(int(v - reach), 0)
    x1, y1 = min(int(u + reach) + 2, width), min(int(v + reach) + 2, height)
    patch = np.ascontiguousarray(image[y0:y1, x0:x1], dtype=np.float32)
    free = [True, True, fit_angle, fit_scale, True, True]
    origin = (u - x0, v - y0)
    first = _State(origin[0], origin[1], angle, scale)
    state = _gauss_newton(
        patch, points, first, free=free, origin=origin, max_move=max_move, iterations=iterations
    )
    if state is None or state.hidden is None:
        return None
    u, v, angle, scale, hidden = state.u, state.v, state.angle, state.scale, state.hidden
    qx, qy, tv, _ = points
    c, s = np.cos(angle), np.sin(angle)
    px = u + scale * (c * qx - s * qy)
    py = v + scale * (s * qx + c * qy)
    seen = _sample(patch, px, py, border=cv2.BORDER_REPLICATE).ravel()
    score = float(np.corrcoef(tv, seen.astype(np.float64))[0, 1])
    return Alignment(
        u=float(u + x0),
        v=float(v + y0),
        angle=float(angle),
        scale=float(scale),
        score=score if np.isfinite(score) else -1.0,
        visible=float(1.0 - hidden.mean()),
        spread=state.spread,
    )
