"""Feature location: where is the part (or its feature) in the image, to sub-pixel accuracy.

Three methods, one function each, and :func:`locate` to dispatch by name (what the server's
configuration names):

- :func:`locate_template` -- normalised cross-correlation with a gray template, optionally
  searching over rotation and scale; several instances with non-maximum suppression; each
  pose refined by robust alignment (:mod:`.template_align`), which occlusion does not pull.
- :func:`locate_circles` -- bright (or dark) round features such as rotor caps seen from above:
  Hough candidates refined by a circle fit to sub-pixel edge points.
- :func:`locate_blobs` -- threshold and connected components, filtered by area and circularity;
  intensity-weighted centroid and second-moment orientation.

Every function takes the image first (``uint8`` gray ``(H, W)`` or BGR ``(H, W, 3)``) and its
options keyword-only, and returns a list of :class:`Feature`, best first. Positions are
``(u, v)`` = (column, row) in **full-image** pixels, the centre of the top-left pixel being
``(0.0, 0.0)`` (docs/conventions.md), even when an ``roi`` restricts the search. Angles are in
radians, measured from the +u axis towards the +v axis (clockwise on the screen).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, replace
from typing import Any, Literal

import cv2
import numpy as np
from numpy.typing import NDArray

from .circle_moments import moment_centre
from .edge_width import SHARP_SIGMA, edge_sigma
from .errors import BadImageError, NotFoundError, RoiError, TemplateError
from .template_align import Alignment, align_template

__all__ = [
    "CENTRES",
    "MAX_SCALE",
    "METHODS",
    "MIN_SCALE",
    "Feature",
    "Rejection",
    "circle_margin_px",
    "crop_roi",
    "locate",
    "locate_blobs",
    "locate_circles",
    "locate_one",
    "locate_template",
    "to_gray",
]

Gray = NDArray[np.uint8]
FloatArray = NDArray[np.float64]
Roi = tuple[int, int, int, int]
Polarity = Literal["bright", "dark"]
Centre = Literal["edge", "moments"]
CENTRES: tuple[Centre, ...] = ("edge", "moments")
"""How :func:`locate_circles` reads a circle's centre (its ``centre`` option)."""


@dataclass(frozen=True)
class Feature:
    """One located feature.

    Attributes
    ----------
    u, v : float
        Sub-pixel position in full-image pixels (column, row).
    angle : float
        Orientation in radians from +u towards +v; 0.0 where it has no meaning (circles).
    score : float
        Method-specific quality, higher is better (see each ``locate_*`` function).
    radius : float or None
        Circle radius in pixels (``circle`` only).
    area : float or None
        Blob area in px² (``blob`` only).
    scale : float or None
        Size relative to the template (``template`` with a scale search only).
    visible : float or None
        ``template`` only: the share (0..1) of the template's pixels that agree with the image
        at the refined pose (hidden ones do not), None where the alignment failed.
    """

    u: float
    v: float
    angle: float = 0.0
    score: float = 0.0
    radius: float | None = None
    area: float | None = None
    scale: float | None = None
    visible: float | None = None


# --- shared input checks ----------------------------------------------------------------------


def to_gray(image: Any, *, what: str = "image") -> Gray:
    """Check an image and return it as a gray ``uint8`` array ``(H, W)``.

    Parameters
    ----------
    image : ndarray
        ``uint8`` ``(H, W)``, ``(H, W, 1)`` or BGR ``(H, W, 3)``.
    what : str
        Name used in the error message.

    Raises
    ------
    BadImageError
        Not a non-empty ``uint8`` gray or BGR array.
    """
    if not isinstance(image, np.ndarray):
        raise BadImageError(f"{what} must be a numpy array, not {type(image).__name__}")
    if image.dtype != np.uint8:
        raise BadImageError(f"{what} must be uint8, not {image.dtype}")
    if image.ndim == 3 and image.shape[2] == 1:
        image = image[:, :, 0]
    if image.ndim == 3 and image.shape[2] == 3:
        if image.shape[0] == 0 or image.shape[1] == 0:
            raise BadImageError(f"{what} is empty: shape {image.shape}")
        return np.asarray(cv2.cvtColor(np.ascontiguousarray(image), cv2.COLOR_BGR2GRAY), np.uint8)
    if image.ndim != 2:
        raise BadImageError(f"{what} must be gray (H, W) or BGR (H, W, 3), not shape {image.shape}")
    if image.size == 0:
        raise BadImageError(f"{what} is empty: shape {image.shape}")
    return np.ascontiguousarray(image)


def crop_roi(gray: Gray, roi: Sequence[int] | None) -> tuple[Gray, Roi]:
    """Cut ``roi`` = ``[u, v, width, height]`` (full-image pixels) out of ``gray``.

    Returns the view and the ROI as a tuple of ints (the whole image when ``roi`` is None).

    Raises
    ------
    RoiError
        Not four integers, empty, or not inside the image.
    """
    height, width = gray.shape
    if roi is None:
        return gray, (0, 0, width, height)
    try:
        values = [v for v in roi]
    except TypeError:
        raise RoiError(f"roi must be [u, v, width, height], not {roi!r}") from None
    if len(values) != 4:
        raise RoiError(f"roi must be [u, v, width, height], not {roi!r}")
    ints = []
    for value in values:
        if isinstance(value, bool) or not isinstance(value, int | float | np.integer | np.floating):
            raise RoiError(f"roi must hold integers, not {roi!r}")
        if not float(value).is_integer():
            raise RoiError(f"roi must hold integers, not {roi!r}")
        ints.append(int(value))
    u, v, w, h = ints
    if w <= 0 or h <= 0:
        raise RoiError(f"roi {ints} is empty")
    if u < 0 or v < 0 or u + w > width or v + h > height:
        raise RoiError(f"roi {ints} does not lie inside the {width}x{height} image")
    return gray[v : v + h, u : u + w], (u, v, w, h)


def _check_polarity(polarity: str) -> None:
    if polarity not in ("bright", "dark"):
        raise ValueError(f"polarity must be 'bright' or 'dark', not {polarity!r}")


# --- sub-pixel helpers ------------------------------------------------------------------------


def _parabola_offset(left: float, centre: float, right: float) -> float:
    """Vertex offset in (-0.5, 0.5) of the parabola through (-1, l), (0, c), (1, r)."""
    denom = left - 2.0 * centre + right
    if denom >= 0.0:  # not a maximum
        return 0.0
    return float(np.clip(0.5 * (left - right) / denom, -0.5, 0.5))


def _quadratic_peak(patch: FloatArray) -> tuple[float, float]:
    """Sub-pixel peak (dx, dy) of a 3x3 patch by a least-squares 2D quadratic.

    Falls back to separable parabolas when the quadric is not a maximum or its vertex lies more
    than one pixel away.
    """
    ys, xs = np.mgrid[-1:2, -1:2]
    x = xs.ravel().astype(np.float64)
    y = ys.ravel().astype(np.float64)
    a = np.stack([np.ones(9), x, y, x * x, x * y, y * y], axis=1)
    c, *_ = np.linalg.lstsq(a, patch.ravel(), rcond=None)
    hess = np.array([[2 * c[3], c[4]], [c[4], 2 * c[5]]])
    if np.linalg.det(hess) > 0 and hess[0, 0] < 0:
        dx, dy = np.linalg.solve(hess, -c[1:3])
        if abs(dx) <= 1.0 and abs(dy) <= 1.0:
            return float(dx), float(dy)
    return (
        _parabola_offset(patch[1, 0], patch[1, 1], patch[1, 2]),
        _parabola_offset(patch[0, 1], patch[1, 1], patch[2, 1]),
    )


# --- template ---------------------------------------------------------------------------------


def _posed_size(side: int, scale: float) -> int:
    """A template side scaled by ``scale``, rounded to keep its parity (so that the scaled
    template's centre stays on the same pixel grid as the original's) and at least 3 px."""
    grown = side + 2 * int(round((scale - 1.0) * side / 2.0))
    return max(grown, 3 if side % 2 else 4)


@dataclass(frozen=True)
class _Posed:
    """The template turned and scaled for one pose of the search.

    ``image`` is the posed template, ``mask`` its inscribed disc (None: the whole rectangle is
    correlated), ``shift`` = ``(dx, dy)``: the posed template's top-left at ``(x, y)`` puts its
    centre where the original template's top-left at ``(x + dx, y + dy)`` would put its own.
    """

    image: Gray
    mask: Gray | None
    shift: tuple[int, int]


def _posed(template: Gray, angle: float, scale: float, rotating: bool) -> _Posed:
    """``template`` turned by ``angle`` (rad, +u towards +v) and scaled by ``scale`` about its
    centre. With rotation only its inscribed disc is correlated, so that scores compare between
    angles; without, the whole (scaled) rectangle."""
    h, w = template.shape
    hs, ws = _posed_size(h, scale), _posed_size(w, scale)
    c, s = math.cos(angle) * scale, math.sin(angle) * scale
    src = ((w - 1) / 2.0, (h - 1) / 2.0)
    dst = ((ws - 1) / 2.0, (hs - 1) / 2.0)
    # dst = centre' + s R (p - centre), R turning +u towards +v (clockwise on the screen).
    matrix = np.array(
        [
            [c, -s, dst[0] - (c * src[0] - s * src[1])],
            [s, c, dst[1] - (s * src[0] + c * src[1])],
        ]
    )
    if angle == 0.0 and scale == 1.0:
        image = template
    else:
        image = np.asarray(
            cv2.warpAffine(
                template, matrix, (ws, hs), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE
            ),
            np.uint8,
        )
    mask = _disc_mask((hs, ws)) if rotating else None
    return _Posed(image, mask, ((ws - w) // 2, (hs - h) // 2))


def _disc_mask(shape: tuple[int, int]) -> Gray:
    h, w = shape
    ys, xs = np.mgrid[0:h, 0:w]
    r = (min(h, w) - 1) / 2.0
    inside = (xs - (w - 1) / 2.0) ** 2 + (ys - (h - 1) / 2.0) ** 2 <= r * r
    return np.where(inside, 255, 0).astype(np.uint8)


def _match(image: Gray, template: Gray, mask: Gray | None) -> NDArray[np.float32]:
    if mask is None:
        result = cv2.matchTemplate(image, template, cv2.TM_CCOEFF_NORMED)
    else:
        result = cv2.matchTemplate(image, template, cv2.TM_CCOEFF_NORMED, mask=mask)
    out: NDArray[np.float32] = np.nan_to_num(result, nan=-1.0, posinf=-1.0, neginf=-1.0)
    return out


def _steps(value_range: tuple[float, float], step: float, what: str) -> FloatArray:
    """``low``, ``low + step``, ... up to ``high`` (always included)."""
    lo, hi = float(value_range[0]), float(value_range[1])
    if not (math.isfinite(lo) and math.isfinite(hi)) or hi < lo:
        raise ValueError(f"{what}_range must be (low, high) with low <= high, not {value_range}")
    if hi == lo:
        return np.array([lo])
    if not step > 0:
        raise ValueError(f"{what}_step must be > 0, not {step}")
    n = int(math.floor((hi - lo) / step + 1e-9)) + 1
    values = lo + step * np.arange(n, dtype=np.float64)
    if hi - values[-1] > 1e-9:
        values = np.append(values, hi)
    return np.asarray(values, np.float64)


def _angles(angle_range: tuple[float, float], angle_step: float) -> FloatArray:
    return _steps(angle_range, angle_step, "angle")


MIN_SCALE, MAX_SCALE = 0.5, 2.0
"""Scales a template search may try (a wider range is a different template)."""


def _scales(scale_range: tuple[float, float], scale_step: float) -> FloatArray:
    scales = _steps(scale_range, scale_step, "scale")
    if scales[0] < MIN_SCALE or scales[-1] > MAX_SCALE:
        raise ValueError(
            f"scale_range must lie within {MIN_SCALE:g}..{MAX_SCALE:g}, not {scale_range}"
        )
    return scales


@dataclass(frozen=True)
class _Grid:
    """The poses searched: every angle at every scale; pose index ``k = i * len(scales) + j``
    for ``angles[i]``, ``scales[j]``."""

    angles: FloatArray
    scales: FloatArray
    rotating: bool

    def __len__(self) -> int:
        return len(self.angles) * len(self.scales)

    def pose(self, k: int) -> tuple[float, float]:
        i, j = divmod(k, len(self.scales))
        return float(self.angles[i]), float(self.scales[j])

    def near(self, k: int) -> list[int]:
        """Pose ``k`` and its neighbours one step away in angle and scale."""
        i, j = divmod(k, len(self.scales))
        return [
            a * len(self.scales) + b
            for a in range(max(i - 1, 0), min(i + 2, len(self.angles)))
            for b in range(max(j - 1, 0), min(j + 2, len(self.scales)))
        ]

    def posed(self, template: Gray, angle: float, scale: float) -> _Posed:
        return _posed(template, angle, scale, self.rotating)


def locate_template(
    image: Any,
    template: Any,
    *,
    roi: Sequence[int] | None = None,
    min_score: float = 0.7,
    max_count: int = 1,
    angle_range: tuple[float, float] = (0.0, 0.0),
    angle_step: float = math.radians(5.0),
    scale_range: tuple[float, float] = (1.0, 1.0),
    scale_step: float = 0.02,
    min_distance: float | None = None,
    pyramid_levels: int | None = None,
    align: bool = True,
) -> list[Feature]:
    """Find instances of a gray template by normalised cross-correlation, over rotation and
    scale.

    Parameters
    ----------
    image : ndarray
        ``uint8`` gray ``(H, W)`` or BGR ``(H, W, 3)``.
    template : ndarray
        ``uint8`` gray ``(h, w)`` (BGR is converted), not constant, no larger than the ROI.
        The located point is the template's centre, ``((w - 1) / 2, (h - 1) / 2)`` in template
        pixels.
    roi : [u, v, width, height], optional
        Search region in full-image pixels; the whole (posed) template must fit inside it.
    min_score : float
        Lowest NCC score (``cv2.TM_CCOEFF_NORMED``, -1..1) reported.
    max_count : int
        Most instances reported.
    angle_range : (float, float)
        Rotations searched, radians (+u towards +v). ``(0, 0)`` (default): no rotation search,
        the whole rectangular template is correlated. Otherwise the template is rotated about its
        centre in steps of ``angle_step`` and only its inscribed disc is correlated (masked NCC),
        so scores are comparable between angles.
    angle_step : float
        Rotation step in radians. The reported angle is interpolated between steps.
    scale_range : (float, float)
        Scales searched (image size of the part / template size), within 0.5..2. ``(1, 1)``
        (default): no scale search. The template is resized about its centre at every step.
    scale_step : float
        Scale step; the reported scale is interpolated between steps. NCC tolerates a scale
        error of about ``1 / (template side in px)`` with little loss of score.
    min_distance : float, optional
        Closest two instances may be, in pixels (default: half the template's smaller side).
    pyramid_levels : int, optional
        Search first on the image halved this many times (over all poses), then only around
        the coarse peaks at full size. None (default): 1 when the template's smaller side is at
        least 32 px, 2 when at least 64 px, provided the search region holds at least 16
        templates; else 0 (exhaustive). Much faster; a template with only very fine texture
        may need 0.
    align : bool
        Refine each instance's pose by robust alignment (:mod:`.template_align`; default).
        False keeps the correlation peak's pose, which an occluder pulls (for comparison).

    Returns
    -------
    list of Feature
        Best first. ``angle`` is the rotation of the instance relative to the template (0
        without a rotation search), ``scale`` its size relative to the template (None without
        a scale search). Position: integer NCC peak refined by a 2D quadratic fit of its 3x3
        neighbourhood, at the interpolated angle and scale.

        ``score`` is the NCC at that pose: 1.0 an exact copy of the template up to brightness
        and contrast (gain and offset), 0 no linear relation, negative an inverted copy. Noise
        and blur lower it a little. An occluder hiding a fraction ``f`` of the correlated area
        lowers it to the NCC of the template with a copy whose hidden pixels show the occluder:
        roughly ``sqrt(1 - f) / sqrt(1 + f * d**2 / var)``, ``d`` the occluder's grey level
        minus the template's mean and ``var`` the template's variance: ~0.87 for a quarter
        hidden by a surface of the template's mean grey, less for a much brighter or darker (or
        textured) occluder (``docs/configuration.md``, locate.template). ``visible`` is the
        share of the template found not hidden (None where the alignment failed and the pose
        is the correlation peak's).

    Raises
    ------
    BadImageError, RoiError, TemplateError
    """
    gray = to_gray(image)
    tmpl = to_gray(template, what="template") if template is not None else None
    if tmpl is None:
        raise TemplateError("no template given")
    if float(tmpl.std()) == 0.0:
        raise TemplateError("the template is constant: normalised correlation is undefined")
    search, (u0, v0, _, _) = crop_roi(gray, roi)
    th, tw = tmpl.shape
    if th > search.shape[0] or tw > search.shape[1]:
        raise TemplateError(
            f"template {tw}x{th} is larger than the search region "
            f"{search.shape[1]}x{search.shape[0]}"
        )
    if max_count < 1:
        return []
    angles = _angles(angle_range, angle_step)
    scales = _scales(scale_range, scale_step)
    grid = _Grid(angles, scales, rotating=len(angles) > 1 or angles[0] != 0.0)
    spacing = min(th, tw) / 2.0 if min_distance is None else float(min_distance)
    levels = _auto_levels(tmpl.shape, search.shape) if pyramid_levels is None else pyramid_levels
    if levels < 0:
        raise ValueError(f"pyramid_levels must be >= 0, not {pyramid_levels}")

    if levels == 0:
        best, best_index = _best_over_poses(search, tmpl, grid, range(len(grid)))
        candidates = [
            (x, y, int(best_index[y, x])) for x, y in _peaks(best, min_score, spacing, max_count)
        ]
    else:
        candidates = _coarse_to_fine(search, tmpl, grid, levels, min_score, spacing, max_count)

    height, width = search.shape[0] - th + 1, search.shape[1] - tw + 1
    features = []
    for x, y, k in _worth_refining(search, tmpl, grid, candidates, min_score, spacing, max_count):
        angle, scale = _refine_pose(search, tmpl, grid, k, x, y)
        local = _local_scores(search, grid.posed(tmpl, angle, scale), x, y)
        dx, dy = _quadratic_peak(local)
        dx = dx if 0 < x < width - 1 else 0.0
        dy = dy if 0 < y < height - 1 else 0.0
        u, v, score = x + dx + (tw - 1) / 2.0, y + dy + (th - 1) / 2.0, float(local[1, 1])
        visible = None
        aligned = _align(search, tmpl, grid, (u, v, angle, scale)) if align else None
        if aligned is not None:
            u, v, angle, scale = aligned.u, aligned.v, aligned.angle, aligned.scale
            score, visible = aligned.score, aligned.visible
        features.append(
            Feature(
                u=u0 + u,
                v=v0 + v,
                angle=angle,
                score=min(score, 1.0),
                scale=scale if len(scales) > 1 or scales[0] != 1.0 else None,
                visible=visible,
            )
        )
    features.sort(key=lambda f: -f.score)
    kept: list[Feature] = []
    for f in features:  # the coarse level may have found one instance twice
        if f.score >= min_score and all(
            (f.u - g.u) ** 2 + (f.v - g.v) ** 2 >= spacing**2 for g in kept
        ):
            kept.append(f)
    return kept[:max_count]


ALIGN_MARGIN = 0.1
"""Candidates whose correlation is this far below ``min_score`` are still aligned: alignment
moves the score by a few hundredths (the sub-pixel pose), never by more."""


def _worth_refining(
    search: Gray,
    tmpl: Gray,
    grid: _Grid,
    candidates: list[tuple[int, int, int]],
    min_score: float,
    spacing: float,
    max_count: int,
) -> list[tuple[int, int, int]]:
    """The candidates worth the (costlier) refinement: best correlation first, one per place,
    at most ``max_count + 2`` of those within ``ALIGN_MARGIN`` of ``min_score``."""
    scored = []
    for x, y, k in candidates:
        score = float(_local_scores(search, grid.posed(tmpl, *grid.pose(k)), x, y)[1, 1])
        if score >= min_score - ALIGN_MARGIN:
            scored.append((score, x, y, k))
    scored.sort(key=lambda c: -c[0])
    kept: list[tuple[int, int, int]] = []
    for _, x, y, k in scored:
        if all((x - a) ** 2 + (y - b) ** 2 >= spacing**2 for a, b, _ in kept):
            kept.append((x, y, k))
    return kept[: max_count + 2]


def _align(
    search: Gray, tmpl: Gray, grid: _Grid, start: tuple[float, float, float, float]
) -> Alignment | None:
    """The correlation's pose refined by robust alignment (:mod:`.template_align`), or None
    where that fails or leaves the searched angles or scales by more than a step.

    With a scale search the alignment also starts from the middle and the far end of the
    scales searched: under occlusion correlation can put the scale at one end of its range, too
    far for the alignment to find its way back. The start whose alignment leaves the smallest
    disagreement among the pixels not hidden wins.
    """
    fit_angle, fit_scale = len(grid.angles) > 1, len(grid.scales) > 1
    u, v, angle, scale = start
    scales = [scale]
    if fit_scale:
        lo, hi = float(grid.scales[0]), float(grid.scales[-1])
        far = lo if abs(scale - hi) < abs(scale - lo) else hi
        scales += [s for s in (0.5 * (lo + hi), far) if abs(s - scale) > 0.5 * (hi - lo) / 4]
    slack_a = float(grid.angles[1] - grid.angles[0]) if fit_angle else 0.0
    slack_s = float(grid.scales[1] - grid.scales[0]) if fit_scale else 0.0
    best: Alignment | None = None
    for begin in scales:
        aligned = align_template(
            search,
            tmpl,
            (u, v, angle, begin),
            disc=grid.rotating,
            fit_angle=fit_angle,
            fit_scale=fit_scale,
            max_move=max(3.0, 0.1 * min(tmpl.shape) * float(grid.scales[-1])),
        )
        if aligned is None:
            continue
        if not grid.angles[0] - slack_a <= aligned.angle <= grid.angles[-1] + slack_a:
            continue
        if not grid.scales[0] - slack_s <= aligned.scale <= grid.scales[-1] + slack_s:
            continue
        if best is None or aligned.spread < best.spread:
            best = aligned
    return best


def _auto_levels(template: tuple[int, int], search: tuple[int, int]) -> int:
    """Coarse levels for a search: halve while the template keeps >= 16 px a side (at most
    twice), and only when the search region is much larger than the template."""
    if search[0] * search[1] < 16 * template[0] * template[1]:
        return 0
    levels = 0
    while levels < 2 and min(template) / 2 ** (levels + 1) >= 16:
        levels += 1
    return levels


def _best_over_poses(
    search: Gray, tmpl: Gray, grid: _Grid, poses: Sequence[int] | range
) -> tuple[NDArray[np.float32], NDArray[np.int32]]:
    """Best NCC map over the ``poses`` (indices into ``grid``), and the pose giving it.

    The maps are indexed like the unposed template's: ``[y, x]`` is the score of the instance
    whose centre is where ``tmpl``'s would be with its top-left at ``(x, y)``. Where a (larger)
    posed template does not fit, its score is -1.
    """
    th, tw = tmpl.shape
    sh, sw = search.shape
    best = np.full((sh - th + 1, sw - tw + 1), -1.0, np.float32)
    best_index = np.full(best.shape, poses[0], np.int32)
    for k in poses:
        posed = grid.posed(tmpl, *grid.pose(k))
        ph, pw = posed.image.shape
        if ph > sh or pw > sw:
            continue
        scores = _match(search, posed.image, posed.mask)
        dx, dy = posed.shift
        # scores[yp, xp] belongs at best[yp + dy, xp + dx].
        x0, y0 = max(dx, 0), max(dy, 0)
        x1 = min(best.shape[1], scores.shape[1] + dx)
        y1 = min(best.shape[0], scores.shape[0] + dy)
        if x1 <= x0 or y1 <= y0:
            continue
        part = scores[y0 - dy : y1 - dy, x0 - dx : x1 - dx]
        target = best[y0:y1, x0:x1]
        better = part > target
        target[better] = part[better]
        best_index[y0:y1, x0:x1][better] = k
    return best, best_index


def _peaks(
    scores: NDArray[np.float32], min_score: float, spacing: float, count: int
) -> list[tuple[int, int]]:
    """Local maxima >= min_score, best first, greedily at least ``spacing`` px apart."""
    peaks = (scores >= cv2.dilate(scores, np.ones((3, 3), np.uint8))) & (scores >= min_score)
    ys, xs = np.nonzero(peaks)
    order = np.argsort(-scores[ys, xs], kind="stable")
    accepted: list[tuple[int, int]] = []
    for i in order:
        x, y = int(xs[i]), int(ys[i])
        if all((x - ax) ** 2 + (y - ay) ** 2 >= spacing**2 for ax, ay in accepted):
            accepted.append((x, y))
            if len(accepted) >= count:
                break
    return accepted


def _coarse_to_fine(
    search: Gray,
    tmpl: Gray,
    grid: _Grid,
    levels: int,
    min_score: float,
    spacing: float,
    max_count: int,
) -> list[tuple[int, int, int]]:
    """Candidates (x, y, pose index) found on a ``levels`` times halved image, then located
    again at full size within ``2**levels + 2`` px and one angle and scale step of the coarse
    peak."""
    small_search, small_tmpl = search, tmpl
    for _ in range(levels):
        if min(small_tmpl.shape) < 16:
            break
        small_search = np.asarray(cv2.pyrDown(small_search), np.uint8)
        small_tmpl = np.asarray(cv2.pyrDown(small_tmpl), np.uint8)
    scale = search.shape[1] / small_search.shape[1]
    best, best_index = _best_over_poses(small_search, small_tmpl, grid, range(len(grid)))
    # Halving blurs the texture, which changes the scores: be generous, decide at full size.
    coarse = _peaks(best, min_score - 0.25, spacing / scale, 2 * max_count + 4)
    th, tw = tmpl.shape
    sth, stw = small_tmpl.shape
    # The largest posed template decides how far the window must reach beyond the template.
    grow = max(_posed_size(max(th, tw), float(grid.scales[-1])) - max(th, tw), 0) // 2 + 1
    reach = int(math.ceil(scale)) + 2
    out = []
    for cx, cy in coarse:
        x = int(round(scale * (cx + (stw - 1) / 2.0) - (tw - 1) / 2.0))
        y = int(round(scale * (cy + (sth - 1) / 2.0) - (th - 1) / 2.0))
        x0, y0 = max(x - reach, 0), max(y - reach, 0)
        x1 = min(x + reach, search.shape[1] - tw)
        y1 = min(y + reach, search.shape[0] - th)
        if x1 < x0 or y1 < y0:
            continue
        # The window keeps a margin of `grow` px round the unposed template's footprint where
        # the search region has it, so that larger poses are scored at the same centres.
        mx0, my0 = min(grow, x0), min(grow, y0)
        wx1 = min(x1 + tw + grow, search.shape[1])
        wy1 = min(y1 + th + grow, search.shape[0])
        window = search[y0 - my0 : wy1, x0 - mx0 : wx1]
        local, local_index = _best_over_poses(
            window, tmpl, grid, grid.near(int(best_index[cy, cx]))
        )
        # Only the offsets inside [x0, x1] x [y0, y1] of the full search.
        inside = local[my0 : my0 + y1 - y0 + 1, mx0 : mx0 + x1 - x0 + 1]
        j, i = np.unravel_index(int(np.argmax(inside)), inside.shape)
        out.append((x0 + int(i), y0 + int(j), int(local_index[my0 + j, mx0 + i])))
    return out


def _local_scores(search: Gray, posed: _Posed, x: int, y: int) -> FloatArray:
    """NCC scores (3, 3) of a posed template whose centre is where the unposed template's is
    with its top-left at (x-1..x+1, y-1..y+1); edges replicate, -1 where it does not fit."""
    th, tw = posed.image.shape
    sh, sw = search.shape
    px, py = x - posed.shift[0], y - posed.shift[1]
    x0, y0 = max(px - 1, 0), max(py - 1, 0)
    x1, y1 = min(px + 1, sw - tw), min(py + 1, sh - th)
    if x1 < x0 or y1 < y0:
        return np.full((3, 3), -1.0)
    patch = search[y0 : y1 + th, x0 : x1 + tw]
    scores = _match(patch, posed.image, posed.mask).astype(np.float64)
    out = np.empty((3, 3))
    for j in range(3):
        for i in range(3):
            yy = min(max(py - 1 + j, y0), y1) - y0
            xx = min(max(px - 1 + i, x0), x1) - x0
            out[j, i] = scores[yy, xx]
    return out


def _refine_pose(
    search: Gray, tmpl: Gray, grid: _Grid, k: int, x: int, y: int
) -> tuple[float, float]:
    """The angle and scale of pose ``k`` interpolated by a parabola through the best local
    score one step either side (angle at the pose's scale, then scale at the refined angle)."""
    i, j = divmod(k, len(grid.scales))
    angle, scale = float(grid.angles[i]), float(grid.scales[j])

    def best_at(a: float, s: float) -> float:
        return float(_local_scores(search, grid.posed(tmpl, a, s), x, y).max())

    if 0 < i < len(grid.angles) - 1:
        s3 = [best_at(float(grid.angles[n]), scale) for n in (i - 1, i, i + 1)]
        step = float(grid.angles[i + 1] - grid.angles[i])
        angle = float(grid.angles[i] + step * _parabola_offset(*s3))
    if 0 < j < len(grid.scales) - 1:
        s3 = [best_at(angle, float(grid.scales[n])) for n in (j - 1, j, j + 1)]
        step = float(grid.scales[j + 1] - grid.scales[j])
        scale = float(grid.scales[j] + step * _parabola_offset(*s3))
    return angle, scale


# --- circles ----------------------------------------------------------------------------------


def _fit_circle_algebraic(points: FloatArray) -> tuple[float, float, float]:
    """Kåsa fit: least squares on x² + y² + D x + E y + F = 0."""
    x, y = points[:, 0], points[:, 1]
    a = np.stack([x, y, np.ones_like(x)], axis=1)
    b = -(x * x + y * y)
    (d, e, f), *_ = np.linalg.lstsq(a, b, rcond=None)
    cx, cy = -d / 2.0, -e / 2.0
    r2 = cx * cx + cy * cy - f
    return float(cx), float(cy), float(math.sqrt(max(r2, 0.0)))


def _fit_circle_geometric(
    points: FloatArray, start: tuple[float, float, float], iterations: int = 10
) -> tuple[float, float, float]:
    """Gauss-Newton on the orthogonal distances |p - c| - r."""
    cx, cy, r = start
    for _ in range(iterations):
        dx = points[:, 0] - cx
        dy = points[:, 1] - cy
        dist = np.hypot(dx, dy)
        dist = np.where(dist < 1e-12, 1e-12, dist)
        residual = dist - r
        jac = np.stack([-dx / dist, -dy / dist, -np.ones_like(dist)], axis=1)
        step, *_ = np.linalg.lstsq(jac, -residual, rcond=None)
        cx, cy, r = cx + step[0], cy + step[1], r + step[2]
        if float(np.abs(step).max()) < 1e-6:
            break
    return float(cx), float(cy), float(r)


# Where the local inner and outer grey levels of an edge are read: this far (px) on either side
# of its steepest step. Near enough not to reach a second edge (a cap's side wall, a few px
# wide), far enough to be outside the anti-aliased and interpolated transition (~±1 px).
_LEVEL_NEAR = 1.5
_LEVEL_FAR = 2.0
# A side is flat when its level _FLAT_FAR px from the step is within _FLATNESS x contrast
# (+ 4 grey levels for noise) of the level used.
_FLAT_FAR = 3.5
_FLATNESS = 0.2


def _edge_points(
    image: FloatArray,
    centre: tuple[float, float],
    radius: float,
    *,
    polarity: Polarity,
    rays: int,
    half_width: float,
    min_contrast: float,
    sigma: float = SHARP_SIGMA,
) -> tuple[FloatArray, FloatArray]:
    """Sub-pixel edge points (n, 2) along radial rays around a circle guess, and their contrasts.

    On each ray the samples (bilinear, 0.25 px apart) within ``half_width`` of the guessed radius
    are searched for the steepest fall (bright) or rise (dark) going outwards; the edge is where
    the profile crosses the 50 % level between the local inner and outer levels (the means
    ``_LEVEL_NEAR`` to ``_LEVEL_FAR`` px either side of the steepest step), found by linear
    interpolation. A ray is dropped when either side is not flat out to ``_FLAT_FAR`` px (a
    second edge close by, e.g. a cap's thin side wall, would bias the 50 % level).

    ``sigma`` is the edge's blur (px, :func:`.edge_width.edge_sigma`): beyond
    :data:`.edge_width.SHARP_SIGMA` every distance above (and the baseline of the steepest
    fall) grows by ``sigma / SHARP_SIGMA``, so that the levels are read where a blurred step has
    settled (2 sigma and more from it) rather than on its slope; the flatness check then looks
    1.5 px beyond them. A sharp edge is read exactly as before.
    """
    step = 0.25
    scale = max(1.0, sigma / SHARP_SIGMA)
    level_near = _LEVEL_NEAR * scale
    level_far = _LEVEL_FAR * scale
    flat_far = level_far + (_FLAT_FAR - _LEVEL_FAR)
    lo = max(radius - half_width - flat_far - 0.5, 0.5)
    hi = radius + half_width + flat_far + 0.5
    radii = np.arange(lo, hi + step / 2, step)
    theta = np.linspace(0.0, 2 * np.pi, rays, endpoint=False)
    cos, sin = np.cos(theta)[:, None], np.sin(theta)[:, None]
    map_x = (centre[0] + cos * radii[None, :]).astype(np.float32)
    map_y = (centre[1] + sin * radii[None, :]).astype(np.float32)
    profiles = cv2.remap(
        image.astype(np.float32),
        map_x,
        map_y,
        cv2.INTER_LINEAR,
        borderMode=cv2.BORDER_CONSTANT,
        borderValue=float("nan"),
    ).astype(np.float64)
    if polarity == "dark":
        profiles = -profiles
    n3 = int(round(level_far / step))
    n2 = int(round(level_near / step))
    n4 = int(round(flat_far / step))
    nb = int(round(2 * scale))  # half-baseline of the steepest fall, samples
    window = (radii >= radius - half_width) & (radii <= radius + half_width)
    idx_window = np.nonzero(window)[0]
    length = profiles.shape[1]
    # All rays at once (this runs for every candidate of every request: a Python loop over the
    # rays held the GIL for most of a circle locate). Means over index ranges come from
    # cumulative sums; rays whose ranges leave the profile are masked out.
    ok: NDArray[np.bool_] = np.asarray(~np.isnan(profiles).any(axis=1), dtype=bool)
    prof = np.where(ok[:, None], profiles, 0.0)
    # Steepest fall going outwards, over a 1 px baseline to resist noise.
    idx_window = idx_window[(idx_window - nb >= 0) & (idx_window + nb < length)]
    if len(idx_window) == 0:
        return np.empty((0, 2)), np.empty(0)
    fall = prof[:, idx_window - nb] - prof[:, idx_window + nb]
    j = idx_window[np.argmax(fall, axis=1)]
    ok &= (j - n4 >= 0) & (j + n4 < length)
    jj = np.clip(j, n4, length - 1 - n4)
    csum = np.concatenate([np.zeros((rays, 1)), np.cumsum(prof, axis=1)], axis=1)
    rows = np.arange(rays)

    def mean(first: NDArray[np.intp], last: NDArray[np.intp]) -> FloatArray:
        """Mean of prof[ray, first..last] (inclusive) for every ray."""
        total = csum[rows, last + 1] - csum[rows, first]
        return np.asarray(total / (last - first + 1), dtype=np.float64)

    inner = mean(jj - n3, jj - n2)
    outer = mean(jj + n2, jj + n3)
    contrast = inner - outer
    inner_far = mean(jj - n4, jj - n4 + (n3 - n2))
    outer_far = mean(jj + n4 - (n3 - n2), jj + n4)
    tolerance = _FLATNESS * contrast + 4.0
    ok &= contrast >= min_contrast
    ok &= (np.abs(inner_far - inner) <= tolerance) & (np.abs(outer_far - outer) <= tolerance)
    level = 0.5 * (inner + outer)
    # The crossing of `level` nearest to j, between j - n2 and j + n2.
    offsets = np.arange(-n2, n2 + 1)
    seg = prof[rows[:, None], jj[:, None] + offsets[None, :]] - level[:, None]
    crossing = (seg[:, :-1] >= 0) & (seg[:, 1:] < 0)
    ok &= crossing.any(axis=1)
    distance = np.where(crossing, np.abs(np.arange(2 * n2) - n2)[None, :], 2 * n2 + 1)
    c = np.argmin(distance, axis=1)
    a, b = seg[rows, c], seg[rows, c + 1]
    with np.errstate(invalid="ignore", divide="ignore"):
        frac = a / (a - b)
    r_edge = radii[np.clip(jj - n2 + c, 0, length - 1)] + frac * step
    keep = np.nonzero(ok)[0]
    points = np.column_stack(
        [centre[0] + cos[keep, 0] * r_edge[keep], centre[1] + sin[keep, 0] * r_edge[keep]]
    )
    return points.reshape(-1, 2), contrast[keep].astype(np.float64)


@dataclass(frozen=True)
class Rejection:
    """A Hough candidate that refinement did not accept, and why (for debugging a setup).

    ``u``, ``v``, ``radius``: the candidate as Hough proposed it (full-image px); ``reason``: a
    short sentence naming the check that failed and its numbers.
    """

    u: float
    v: float
    radius: float
    reason: str


def _refine_circle(
    image: FloatArray,
    guess: tuple[float, float, float],
    *,
    polarity: Polarity,
    rays: int,
    min_contrast: float,
    sigma: float,
) -> tuple[tuple[float, float, float], float] | str:
    """Fit a circle to sub-pixel edge points; ((u, v, r), inlier fraction), or why not (str).

    ``sigma`` is the edge blur in px (see :func:`_edge_points`); the fitted circle's inliers
    are the edge points within ``max(1, sigma)`` px of it.
    """
    cx, cy, r = guess
    scale = max(1.0, sigma / SHARP_SIGMA)
    half_width = max(3.0, 0.1 * r, 2.0 * scale)
    needed = max(8, rays // 4)
    band = 1.0
    fraction = 0.0
    for _ in range(3):
        points, _contrast = _edge_points(
            image,
            (cx, cy),
            r,
            polarity=polarity,
            rays=rays,
            half_width=half_width,
            min_contrast=min_contrast,
            sigma=sigma,
        )
        if len(points) < needed:
            return (
                f"edge found on {len(points)} of {rays} rays (needs {needed}): contrast below "
                f"{min_contrast:g} grey levels, or no flat level either side of the edge"
            )
        fit = _fit_circle_algebraic(points)
        fit = _fit_circle_geometric(points, fit)
        for _ in range(3):  # drop outliers (e.g. a shadow or a neighbour), refit
            residual = np.abs(np.hypot(points[:, 0] - fit[0], points[:, 1] - fit[1]) - fit[2])
            mad = float(np.median(residual))
            keep = residual <= max(3.0 * 1.4826 * mad, 0.25)
            if keep.sum() < needed:
                return f"only {int(keep.sum())} edge points agree on one circle (needs {needed})"
            fit = _fit_circle_geometric(points[keep], fit)
        residual = np.abs(np.hypot(points[:, 0] - fit[0], points[:, 1] - fit[1]) - fit[2])
        fraction = float((residual <= band).sum()) / rays
        moved = math.hypot(fit[0] - cx, fit[1] - cy) + abs(fit[2] - r)
        cx, cy, r = fit
        half_width = 2.0 * scale
        if moved < 0.01:
            break
    if not (math.isfinite(cx) and math.isfinite(cy) and r > 0):
        return "the circle fit diverged"
    return (cx, cy, r), fraction


_SMOOTHING = 1.5
"""Smoothing of a blurred candidate's patch, as a multiple of its edge sigma. More quiets the
noise on a shallow edge (rendered discs at sigma 4 px, 40 % contrast: worst centre error 0.12
px at 1x, 0.08 px at 1.5x) but mixes more of a real part's rim relief into its edge (worn
coins move further from their sharp answer); 1.5 keeps round parts within 0.1 px."""


def _denoised(
    image: FloatArray, guess: tuple[float, float, float], sigma: float, smoothing: float
) -> tuple[FloatArray, tuple[int, int], float]:
    """The part of ``image`` around a candidate that refinement reads, smoothed for its blur.

    A blurred edge is shallow: camera noise of a few grey levels moves its 50 % crossing by a
    sizeable fraction of a pixel on every ray, and neighbouring rays share pixels, so the errors
    do not average out. Smoothing with a Gaussian ``_SMOOTHING`` times as wide as the blur
    already there removes most of the noise and moves neither a straight edge's 50 % level nor a
    circle's centre (only its radius, by about sigma² / 2r). Sharp edges are left as they are.

    Returns the patch, its top-left corner ``(x0, y0)`` in ``image``'s pixels and the edge
    sigma now seen in it (px): ``sqrt(1 + _SMOOTHING²) * sigma`` after smoothing.
    """
    if sigma <= SHARP_SIGMA:
        return image, (0, 0), sigma
    cx, cy, r = guess
    margin = r + 2.0 * r * 0.1 + 16.0 * sigma + 8.0
    height, width = image.shape
    x0, y0 = max(int(cx - margin), 0), max(int(cy - margin), 0)
    x1, y1 = min(int(cx + margin) + 1, width), min(int(cy + margin) + 1, height)
    patch = cv2.GaussianBlur(
        np.ascontiguousarray(image[y0:y1, x0:x1]),
        (0, 0),
        smoothing * sigma,
        borderType=cv2.BORDER_REPLICATE,
    )
    return np.asarray(patch, np.float64), (x0, y0), math.sqrt(1.0 + smoothing**2) * sigma


_SMOOTHINGS = (_SMOOTHING, 1.0)
"""Smoothings (multiples of the edge sigma) a blurred candidate is read with, in turn, until
one gives a circle. The wider one reads the levels further from the edge (2 seen sigmas), where
a neighbour 10 px away can already be: a worn coin at sigma 4 px, full contrast, kept 36 of its
180 rays flat (45 needed) at 1.5 and all its outline at 1.0. Narrower than 1.0 lets noise
through: 0.75 read a circle (score 0.60) into the Hubble deep field at sigma 4."""
_MAX_EDGE_DENSITY = 0.15
_SHARP_TRUSTED = 0.8
"""Score from which a candidate's sharp reading is kept without trying the blurred one. A sharp
reading that sees most of the outline is the most precise (rendered caps blurred 2 px: median
0.04 px from the sharp image's answer, against 0.18 px read as blurred, the cap's side wall
merging into its rim); one that sees less on a blurred edge can be off by 0.1 px or more."""
"""Largest share of edge pixels (Canny, half size) for which the classic Hough pass runs: its
cost grows with the edges' count (seconds on pure noise, where it would find nothing)."""


def _hough_candidates(
    hough: Gray, radius_range: tuple[float, float], threshold: float, max_count: int
) -> FloatArray:
    """Circle candidates (n, 3) = (u, v, r) in ROI pixels, the gradient-ALT ones first.

    ``HOUGH_GRADIENT_ALT`` (``threshold``: its "perfectness", 0..1) is precise and rarely
    proposes junk, but on heavily blurred parts (sigma 3..4 px) it misses a few in ten whatever
    its settings. OpenCV's classic ``HOUGH_GRADIENT`` (votes of gradient directions) on the
    image halved (blur loses nothing there) finds those; it runs only when at most
    ``_MAX_EDGE_DENSITY`` of the halved image is edge. Refinement decides, so the union costs
    only a few more refinements: classic candidates within half a radius of an ALT one are
    dropped, and at most ``2 * max_count + 4`` of them are kept.
    """
    r_lo, r_hi = radius_range
    alt = cv2.HoughCircles(
        hough,
        cv2.HOUGH_GRADIENT_ALT,
        dp=1.5,
        minDist=max(r_lo, 2.0),
        param1=150,
        param2=threshold,
        minRadius=int(math.floor(r_lo)),
        maxRadius=int(math.ceil(r_hi)),
    )
    first = np.empty((0, 3)) if alt is None else alt.reshape(-1, 3).astype(np.float64)
    half = np.asarray(cv2.pyrDown(hough), np.uint8)
    if r_lo < 4.0 or float(cv2.Canny(half, 50, 100).mean()) / 255.0 > _MAX_EDGE_DENSITY:
        return first
    classic = cv2.HoughCircles(
        half,
        cv2.HOUGH_GRADIENT,
        dp=1.0,
        minDist=max(r_lo / 2.0, 2.0),
        param1=100,
        param2=10,
        minRadius=int(math.floor(r_lo / 2.0)),
        maxRadius=int(math.ceil(r_hi / 2.0)),
    )
    extra: list[FloatArray] = []
    if classic is not None:
        # Half-size pixel centres: full = 2 * half + 0.5.
        for c in classic.reshape(-1, 3).astype(np.float64)[: 2 * max_count + 4]:
            full = np.array([2.0 * c[0] + 0.5, 2.0 * c[1] + 0.5, 2.0 * c[2]])
            taken = np.concatenate([first, np.array(extra).reshape(-1, 3)])
            if not (np.hypot(taken[:, 0] - full[0], taken[:, 1] - full[1]) < 0.5 * full[2]).any():
                extra.append(full)
    return np.concatenate([first, np.array(extra).reshape(-1, 3)])


def _hough_input(search: Gray) -> Gray:
    """The ROI as Hough should see it: lightly smoothed and stretched to the full grey range.

    ``HOUGH_GRADIENT_ALT``'s Canny thresholds are fixed grey-level gradients; a dim or blurred
    part (contrast 40 %, sigma 4 px) stays under them. Stretching the 1st..99th percentile to
    0..255 makes the thresholds relative to the scene's own contrast; refinement still works on
    the original grey levels, so this cannot create a part.
    """
    smooth = cv2.GaussianBlur(search, (5, 5), 1.0)
    # Percentiles from the histogram: np.percentile sorts the whole ROI (~8 ms at 1024x768).
    cumulative = np.cumsum(cv2.calcHist([smooth], [0], None, [256], [0, 256]).ravel())
    lo, hi = (float(np.searchsorted(cumulative, q * cumulative[-1])) for q in (0.01, 0.99))
    if hi - lo < 1.0:
        return np.asarray(smooth, np.uint8)
    gain = min(255.0 / (hi - lo), 4.0)  # at most 4x: noise must not become edges
    table = np.clip((np.arange(256, dtype=np.float64) - lo) * gain + 0.5, 0, 255)
    return np.asarray(cv2.LUT(smooth, table.astype(np.uint8)), np.uint8)


def _refine_candidate(
    sample: FloatArray,
    guess: tuple[float, float, float],
    *,
    polarity: Polarity,
    rays: int,
    min_contrast: float,
    accept: Callable[[tuple[float, float, float], float], bool],
    edge_sigma_px: float | None,
    max_edge_sigma_px: float,
) -> tuple[tuple[float, float, float], float] | str:
    """Refine one Hough candidate: as a sharp edge first, as a blurred one where that fails.

    The sharp reading (levels 1.5..2 px from the step, no smoothing) is the most precise where
    it works: it drops the rays where a second edge is near, such as a cap's side wall that a
    blurred reading would merge into the rim. Where it finds too few rays, a fit that ``accept``
    refuses or a score below ``_SHARP_TRUSTED``, the edge sigma is measured (or
    ``edge_sigma_px`` taken) and, if the edge is blurred, the candidate is read again with
    windows scaled to it on a smoothed patch (less smoothed, :data:`_SMOOTHINGS`, where that
    fails).
    Returns ((u, v, r), score) in ``sample``'s pixels, or why not (str).
    """
    sharp: tuple[tuple[float, float, float], float] | str | None = None
    if edge_sigma_px is None or edge_sigma_px <= SHARP_SIGMA:
        sharp = _refine_circle(
            sample,
            guess,
            polarity=polarity,
            rays=rays,
            min_contrast=min_contrast,
            sigma=SHARP_SIGMA,
        )
        if not isinstance(sharp, str) and accept(*sharp) and sharp[1] >= _SHARP_TRUSTED:
            return sharp
    sigma = edge_sigma_px
    if sigma is None:
        sigma = edge_sigma(sample, guess[:2], guess[2], polarity=polarity)
        if sigma is None:
            return sharp if sharp is not None else "no edge of the right polarity on most rays"
    if sigma <= SHARP_SIGMA:
        assert sharp is not None
        return sharp if not isinstance(sharp, str) else f"{sharp} (edge sigma {sigma:.2f} px)"
    if sigma > max_edge_sigma_px:
        return f"edge sigma {sigma:.2f} px > max_edge_sigma_px {max_edge_sigma_px:g}"
    blurred: tuple[tuple[float, float, float], float] | str = ""
    for smoothing in _SMOOTHINGS:
        patch, (px, py), seen_sigma = _denoised(sample, guess, sigma, smoothing)
        blurred = _refine_circle(
            patch,
            (guess[0] - px, guess[1] - py, guess[2]),
            polarity=polarity,
            rays=rays,
            min_contrast=min_contrast,
            sigma=seen_sigma,
        )
        if not isinstance(blurred, str):
            break
    if isinstance(blurred, str):
        return f"{blurred} (edge sigma {sigma:.2f} px)"
    (fx, fy, fr), score = blurred
    return (fx + px, fy + py, fr), score


def locate_circles(
    image: Any,
    *,
    roi: Sequence[int] | None = None,
    radius_range: tuple[float, float] = (5.0, 200.0),
    polarity: Polarity = "bright",
    min_score: float = 0.6,
    max_count: int = 10,
    min_contrast: float = 15.0,
    rays: int = 180,
    hough_threshold: float = 0.6,
    edge_sigma_px: float | None = None,
    max_edge_sigma_px: float = 6.0,
    centre: Centre = "edge",
    rejected: list[Rejection] | None = None,
) -> list[Feature]:
    """Find round features (e.g. rotor caps seen from above) with sub-pixel centres.

    Candidates come from :func:`cv2.HoughCircles` (``HOUGH_GRADIENT_ALT``) on the lightly
    smoothed, contrast-stretched ROI (:func:`_hough_input`). Each is refined: its edge blur is
    measured (:func:`.edge_width.edge_sigma`, unless ``edge_sigma_px`` fixes it); along ``rays``
    radial rays the edge is found where the intensity profile crosses 50 % between its local
    inner and outer levels, read far enough from the step for that blur (linear interpolation
    between bilinear samples 0.25 px apart); a circle is fitted to these points, algebraically
    (Kåsa) and then geometrically (Gauss-Newton on orthogonal distances) with outliers beyond 3
    robust standard deviations dropped; rays are re-cast from the new centre until it settles.
    The 50 % level of a blurred step stays where the sharp step was, so blur moves the radius
    slightly (by about sigma² / 2r inwards) but not the centre.

    Parameters
    ----------
    image : ndarray
        ``uint8`` gray ``(H, W)`` or BGR ``(H, W, 3)``.
    roi : [u, v, width, height], optional
        Search region in full-image pixels. A circle must lie wholly inside it to be refined.
    radius_range : (float, float)
        Smallest and largest radius, pixels.
    polarity : {'bright', 'dark'}
        A disc brighter (default) or darker than its surroundings.
    min_score : float
        Lowest score reported (see Returns).
    max_count : int
        Most circles reported.
    min_contrast : float
        Smallest grey-level step across the edge for a ray to count.
    rays : int
        Number of radial rays.
    hough_threshold : float
        ``param2`` of ``HOUGH_GRADIENT_ALT``: the circle "perfectness" (0..1) a candidate needs.
    edge_sigma_px : float, optional
        The edges' blur as a Gaussian sigma in px; None (default): measured per candidate.
    max_edge_sigma_px : float
        Largest blur accepted (px); a candidate whose measured edge is wider is rejected.
    centre : {'edge', 'moments'}
        ``'edge'`` (default): the centre of the circle fitted to the edge points, the part's
        outline. ``'moments'``: the first moment of the background-subtracted intensity around
        each fitted circle, taken at a common blur (:func:`.circle_moments.moment_centre`):
        blur does not move it, but it is the centre of the part's light, not of its outline
        (a part lit from one side reads off towards the light). A part whose moments cannot be
        taken is rejected with the reason. ``radius`` and ``score`` stay the edge fit's.
    rejected : list, optional
        When given, a :class:`Rejection` is appended for every Hough candidate not reported.

    Returns
    -------
    list of Feature
        Best first, ``radius`` in px, ``angle`` 0. ``score`` is the fraction (0..1) of rays
        whose edge point lies within ``max(1, sigma)`` px of the fitted circle: the share of the
        outline seen.

    Raises
    ------
    BadImageError, RoiError
    """
    _check_polarity(polarity)
    if centre not in CENTRES:
        raise ValueError(f"centre must be one of {CENTRES}, not {centre!r}")
    gray = to_gray(image)
    search, (u0, v0, _, _) = crop_roi(gray, roi)
    r_lo, r_hi = float(radius_range[0]), float(radius_range[1])
    if not 0 < r_lo <= r_hi:
        raise ValueError(f"radius_range must be (low, high) with 0 < low <= high: {radius_range}")
    if edge_sigma_px is not None and not 0 < edge_sigma_px <= max_edge_sigma_px:
        raise ValueError(
            f"edge_sigma_px must be in (0, max_edge_sigma_px={max_edge_sigma_px:g}], "
            f"not {edge_sigma_px}"
        )
    if max_count < 1:
        return []
    candidates = _hough_candidates(_hough_input(search), (r_lo, r_hi), hough_threshold, max_count)
    if len(candidates) == 0:
        return []
    # Candidates come from the ROI, but their edges are read on the ROI and a margin around
    # it (within the image): a circle whose centre is in the ROI and whose outline comes near
    # its edge is then seen whole. Read on the crop alone, the rays' flat levels beyond the
    # edge fell outside it and the circle lost its score.
    sample, (du, dv) = _with_margin(gray, (u0, v0, *search.shape[::-1]), r_hi, max_edge_sigma_px)
    height, width = search.shape
    image_h, image_w = gray.shape
    features: list[Feature] = []
    limit = 4 * max_count + 8

    def reject(cx: float, cy: float, r: float, reason: str) -> None:
        if rejected is not None:
            rejected.append(Rejection(u0 + float(cx), v0 + float(cy), float(r), reason))

    for index, (cx, cy, r) in enumerate(candidates):
        if index >= limit:
            reject(cx, cy, r, f"not examined: only the first {limit} candidates are")
            continue
        refined = _refine_candidate(
            sample,
            (float(cx) + du, float(cy) + dv, float(r)),
            polarity=polarity,
            rays=rays,
            min_contrast=min_contrast,
            accept=lambda fit, score: r_lo <= fit[2] <= r_hi and score >= min_score,
            edge_sigma_px=edge_sigma_px,
            max_edge_sigma_px=max_edge_sigma_px,
        )
        if isinstance(refined, str):
            reject(cx, cy, r, refined)
            continue
        (fx, fy, fr), score = refined
        fx, fy = fx - du, fy - dv  # back to the ROI's pixels
        if not r_lo <= fr <= r_hi:
            reject(cx, cy, r, f"fitted radius {fr:.1f} px outside {r_lo:g}..{r_hi:g}")
            continue
        if score < min_score:
            reject(cx, cy, r, f"score {score:.2f} (share of the outline seen) < {min_score:g}")
            continue
        if not (-0.5 <= fx <= width - 0.5 and -0.5 <= fy <= height - 0.5):
            reject(cx, cy, r, f"the fitted centre ({u0 + fx:.1f}, {v0 + fy:.1f}) leaves the ROI")
            continue
        u, v = u0 + fx, v0 + fy
        if u - fr < -0.5 or v - fr < -0.5 or u + fr > image_w - 0.5 or v + fr > image_h - 0.5:
            reject(cx, cy, r, "the fitted circle leaves the image")
            continue
        # Within half a radius (of either) of one already taken: the same part, or a ring of
        # relief inside it (a coin's inner border), not a second part.
        if any(
            math.hypot(fx - (f.u - u0), fy - (f.v - v0)) < 0.5 * max(fr, f.radius or 0.0)
            for f in features
        ):
            reject(cx, cy, r, "the same circle as a better candidate")
            continue
        features.append(Feature(u=u0 + fx, v=v0 + fy, angle=0.0, score=score, radius=fr))
    if centre == "moments":
        features = _moment_centres(
            sample,
            features,
            (u0 - du, v0 - dv),
            polarity=polarity,
            edge_sigma_px=edge_sigma_px,
            reject=reject,
        )
    features.sort(key=lambda f: -f.score)
    for extra in features[max_count:]:
        reject(extra.u - u0, extra.v - v0, extra.radius or 0.0, f"beyond max_count {max_count}")
    return features[:max_count]


def circle_margin_px(max_radius: float, max_sigma: float) -> int:
    """How far beyond an ROI (px) the edge rays of a circle centred in it may read: its
    radius and the flat levels beyond an edge blurred up to ``max_sigma`` px."""
    return int(math.ceil(max_radius + 6.0 * max(max_sigma, 1.0))) + 4


def _with_margin(
    gray: Gray, roi: tuple[int, int, int, int], max_radius: float, max_sigma: float
) -> tuple[FloatArray, tuple[int, int]]:
    """The ROI and a margin around it, cut to the image, as float64, and where the ROI's
    top-left lies in it (px). The margin covers a circle of ``max_radius`` centred anywhere in
    the ROI and the flat levels its rays read beyond an edge blurred up to ``max_sigma``."""
    u0, v0, w, h = roi
    margin = circle_margin_px(max_radius, max_sigma)
    left, top = max(0, u0 - margin), max(0, v0 - margin)
    right = min(gray.shape[1], u0 + w + margin)
    bottom = min(gray.shape[0], v0 + h + margin)
    return gray[top:bottom, left:right].astype(np.float64), (u0 - left, v0 - top)


def _moment_centres(
    sample: FloatArray,
    features: list[Feature],
    origin: tuple[int, int],
    *,
    polarity: Polarity,
    edge_sigma_px: float | None,
    reject: Callable[[float, float, float, str], None],
) -> list[Feature]:
    """``features`` (full-image px) with their centres read as intensity moments in ``sample``
    (the ROI, whose top-left is ``origin``); every other found circle is a neighbour."""
    u0, v0 = origin
    circles = [(f.u - u0, f.v - v0, f.radius or 0.0) for f in features]
    sigmas = [
        edge_sigma_px
        if edge_sigma_px is not None
        else edge_sigma(sample, (cx, cy), r, polarity=polarity) or SHARP_SIGMA
        for cx, cy, r in circles
    ]
    # Two rounds: the second sees its neighbours as their moments put them (their size then
    # no longer depends on the blur either).
    found: list[tuple[float, float, float] | str] = list(circles)
    for _ in range(2):
        neighbours = [c if isinstance(c, tuple) else e for c, e in zip(found, circles, strict=True)]
        found = [
            moment_centre(
                sample,
                circle,
                blur_sigma_px=sigma,
                polarity=polarity,
                others=neighbours[:index] + neighbours[index + 1 :],
            )
            for index, (circle, sigma) in enumerate(zip(circles, sigmas, strict=True))
        ]
    moved: list[Feature] = []
    for feature, circle, result in zip(features, circles, found, strict=True):
        if isinstance(result, str):
            reject(*circle, f"centre by moments: {result}")
        else:
            moved.append(replace(feature, u=u0 + result[0], v=v0 + result[1]))
    return moved


# --- blobs ------------------------------------------------------------------------------------


def locate_blobs(
    image: Any,
    *,
    roi: Sequence[int] | None = None,
    threshold: float | Literal["otsu"] | None = None,
    polarity: Polarity = "bright",
    min_area: float = 10.0,
    max_area: float | None = None,
    min_circularity: float = 0.0,
    min_score: float = 0.0,
    max_count: int = 10,
) -> list[Feature]:
    """Find blobs: connected regions above (bright) or below (dark) a threshold.

    Parameters
    ----------
    image : ndarray
        ``uint8`` gray ``(H, W)`` or BGR ``(H, W, 3)``.
    roi : [u, v, width, height], optional
        Search region in full-image pixels.
    threshold : float or 'otsu', optional
        Grey level (0..255); a pixel belongs to a blob when ``> threshold`` (bright) or
        ``< threshold`` (dark). None or ``'otsu'``: Otsu's threshold of the ROI.
    polarity : {'bright', 'dark'}
    min_area, max_area : float
        Accepted blob area in px² (pixel count of the thresholded region).
    min_circularity : float
        Lowest ``4π·area / perimeter²`` (1 for a disc, ~0.785 for a square; the perimeter is
        that of the pixel outline, so small discs score below 1).
    min_score : float
        Lowest score (= area, px²) reported.
    max_count : int
        Most blobs reported.

    Returns
    -------
    list of Feature
        Largest first. ``score`` = ``area`` = the anti-aliasing-aware area in px²: the sum of
        per-pixel weights ``clip((I - background) / (blob - background), 0, 1)`` over the blob
        grown by 2 px, with the blob and background levels the medians of its interior and of a
        ring around it. (u, v) is the centroid of these weights, ``angle`` the major axis of
        their second moments, in (-π/2, π/2].

    Raises
    ------
    BadImageError, RoiError
    """
    _check_polarity(polarity)
    gray = to_gray(image)
    search, (u0, v0, _, _) = crop_roi(gray, roi)
    if max_count < 1:
        return []
    work = search if polarity == "bright" else (255 - search)
    if threshold is None or threshold == "otsu":
        _, binary = cv2.threshold(work, 0, 255, cv2.THRESH_BINARY | cv2.THRESH_OTSU)
    else:
        t = float(threshold) if polarity == "bright" else 255.0 - float(threshold)
        binary = np.where(work > t, 255, 0).astype(np.uint8)
    count, labels, stats, _ = cv2.connectedComponentsWithStats(binary, connectivity=8)
    values = work.astype(np.float64)
    height, width = work.shape
    kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (5, 5))
    features: list[Feature] = []
    for label in range(1, count):
        pixels = int(stats[label, cv2.CC_STAT_AREA])
        if pixels < min_area or (max_area is not None and pixels > max_area):
            continue
        x, y, w, h = (int(s) for s in stats[label, :4])
        x0, y0 = max(x - 6, 0), max(y - 6, 0)
        x1, y1 = min(x + w + 6, width), min(y + h + 6, height)
        mask = (labels[y0:y1, x0:x1] == label).astype(np.uint8)
        contours, _ = cv2.findContours(mask, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)
        perimeter = sum(cv2.arcLength(c, True) for c in contours)
        circularity = 4.0 * math.pi * pixels / perimeter**2 if perimeter > 0 else 0.0
        if circularity < min_circularity:
            continue
        grown = cv2.dilate(mask, kernel)
        ring = (cv2.dilate(grown, kernel) > 0) & (grown == 0) & (labels[y0:y1, x0:x1] == 0)
        core = cv2.erode(mask, kernel)
        patch = values[y0:y1, x0:x1]
        fg = float(np.median(patch[core > 0])) if core.any() else float(patch[mask > 0].max())
        bg = float(np.median(patch[ring > 0])) if ring.any() else float(patch[mask == 0].mean())
        if fg - bg <= 1e-6:
            weights = mask.astype(np.float64)
        else:
            weights = np.clip((patch - bg) / (fg - bg), 0.0, 1.0) * (grown > 0)
        # Only this blob's pixels and the unlabelled ones around it (not a neighbour's).
        weights *= (labels[y0:y1, x0:x1] == label) | (labels[y0:y1, x0:x1] == 0)
        m = cv2.moments(weights.astype(np.float32), binaryImage=False)
        if m["m00"] <= 0:
            continue
        cx, cy = m["m10"] / m["m00"], m["m01"] / m["m00"]
        angle = 0.5 * math.atan2(2.0 * m["mu11"], m["mu20"] - m["mu02"])
        if angle <= -math.pi / 2:
            angle += math.pi
        area = float(m["m00"])
        if area < min_score:
            continue
        features.append(Feature(u=u0 + x0 + cx, v=v0 + y0 + cy, angle=angle, score=area, area=area))
    features.sort(key=lambda f: -f.score)
    return features[:max_count]


# --- dispatcher -------------------------------------------------------------------------------

METHODS = ("template", "circle", "blob")


def locate(
    image: Any,
    *,
    method: str,
    roi: Sequence[int] | None = None,
    template: Any = None,
    **options: Any,
) -> list[Feature]:
    """Locate features by the named ``method`` (the server's configuration names it).

    ``method`` is one of :data:`METHODS`: ``"template"`` calls :func:`locate_template` (needs
    ``template``), ``"circle"``
    :func:`locate_circles`, ``"blob"`` :func:`locate_blobs`; ``roi`` and the remaining keyword
    options go to that function unchanged (an unknown option raises ``TypeError``).

    Raises
    ------
    ValueError
        Unknown method.
    BadImageError, RoiError, TemplateError
        As the method does.
    """
    if method == "template":
        if template is None:
            raise TemplateError("method 'template' needs a template")
        return locate_template(image, template, roi=roi, **options)
    if template is not None:
        raise ValueError(f"method {method!r} takes no template")
    if method == "circle":
        return locate_circles(image, roi=roi, **options)
    if method == "blob":
        return locate_blobs(image, roi=roi, **options)
    raise ValueError(f"unknown locate method {method!r}; expected one of {METHODS}")


def locate_one(image: Any, **kwargs: Any) -> Feature:
    """The best feature of :func:`locate` (same arguments); NotFoundError if there is none."""
    found = locate(image, **kwargs)
    if not found:
        raise NotFoundError(f"no {kwargs.get('method', '?')} feature found")
    return found[0]
