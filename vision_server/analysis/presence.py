"""ROI presence measures (the paper's quality control, section 2.4 and Figure 4: is the magnet
placed beside the rotor core?).

Each measure turns the ROI into one number; the server compares it with the ``[min, max]`` pass
range of the configuration. :func:`measure_presence` returns the number,
:func:`measure_presence_details` the number with what an overlay can show (the threshold used,
where the template matched, the blobs counted).

Images are ``uint8`` gray ``(H, W)`` or BGR ``(H, W, 3)``; the ROI is ``[u, v, width, height]``
in full-image pixels (None: the whole image); positions are ``(u, v)`` full-image pixels.

Choosing a measure (see tests/vision_server/analysis/test_presence.py for measured accuracies):

- ``dark_fraction`` / ``bright_fraction`` with a **fixed** ``threshold`` half-way between the
  part's and the background's grey levels: simple and robust to moderate lighting changes.
  With ``threshold=None`` Otsu's threshold is computed on the ROI itself, which splits even a
  uniform (part absent) ROI in two halves of its noise: use Otsu only when both part and
  background are always in the ROI.
- ``blob_count``: like ``dark_fraction`` but ignores specks smaller than ``min_blob_area``.
- ``template_score``: independent of brightness and contrast (normalised correlation); needs a
  template image of the part.
- ``edge_density``: independent of the absolute level; needs a part with clear edges on a
  plain background.
- ``mean_intensity``: the simplest, and the most sensitive to lighting.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any, Literal

import cv2
import numpy as np

from .errors import TemplateError
from .locate import Gray, Polarity, crop_roi, to_gray

__all__ = [
    "CANNY_HIGH",
    "CANNY_LOW",
    "MEASURES",
    "Measure",
    "PresenceResult",
    "measure_presence",
    "measure_presence_details",
]

Measure = Literal[
    "mean_intensity",
    "dark_fraction",
    "bright_fraction",
    "edge_density",
    "blob_count",
    "template_score",
]

MEASURES: tuple[str, ...] = (
    "mean_intensity",
    "dark_fraction",
    "bright_fraction",
    "edge_density",
    "blob_count",
    "template_score",
)
"""The measures :func:`measure_presence` computes."""

CANNY_LOW = 50.0
"""Default lower hysteresis threshold of ``edge_density`` (3x3 Sobel, L1 gradient)."""
CANNY_HIGH = 150.0
"""Default upper hysteresis threshold of ``edge_density``."""


@dataclass(frozen=True)
class PresenceResult:
    """One presence measure over an ROI.

    Attributes
    ----------
    measure : str
        One of :data:`MEASURES`.
    value : float
        The measure: grey level 0..255 (``mean_intensity``), fraction 0..1 (``dark_fraction``,
        ``bright_fraction``, ``edge_density``), count (``blob_count``) or NCC -1..1
        (``template_score``).
    roi : (int, int, int, int)
        The ROI measured, ``(u, v, width, height)`` in full-image pixels.
    threshold : float or None
        Grey level used by ``dark_fraction``, ``bright_fraction`` and ``blob_count`` (the given
        one, or Otsu's); None for the other measures.
    location : (float, float) or None
        ``template_score``: the centre of the best match; ``blob_count``: the centroid of the
        largest blob counted (None when there is none); None otherwise. Full-image pixels.
    blobs : tuple of (int, int, int, int)
        ``blob_count``: bounding boxes ``(u, v, width, height)`` of the blobs counted, largest
        first, full-image pixels.
    """

    measure: str
    value: float
    roi: tuple[int, int, int, int]
    threshold: float | None = None
    location: tuple[float, float] | None = None
    blobs: tuple[tuple[int, int, int, int], ...] = field(default=())


def measure_presence(
    image: Any,
    *,
    measure: str,
    roi: Sequence[int] | None = None,
    threshold: float | None = None,
    template: Any = None,
    min_blob_area: int = 20,
    polarity: Polarity = "dark",
    canny: tuple[float, float] = (CANNY_LOW, CANNY_HIGH),
) -> float:
    """One presence measure over the ROI, to compare with a ``[min, max]`` pass range.

    Parameters
    ----------
    image : ndarray
        ``uint8`` gray ``(H, W)`` or BGR ``(H, W, 3)``.
    measure : str
        ``"mean_intensity"``: mean grey level of the ROI, 0..255.
        ``"dark_fraction"`` / ``"bright_fraction"``: fraction (0..1) of ROI pixels
        ``< threshold`` / ``> threshold``.
        ``"edge_density"``: Canny edge pixels per ROI pixel (0..1), hysteresis thresholds
        ``canny`` on the 3x3 Sobel gradient (L1 norm), no smoothing.
        ``"blob_count"``: number of 8-connected regions of ``polarity`` (dark: ``< threshold``,
        bright: ``> threshold``) with at least ``min_blob_area`` pixels.
        ``"template_score"``: best normalised cross-correlation (``TM_CCOEFF_NORMED``, -1..1)
        of ``template`` anywhere inside the ROI.
    roi : [u, v, width, height], optional
        Full-image pixels; None measures the whole image.
    threshold : float, optional
        Grey level 0..255 for the fraction and blob measures; None: Otsu's threshold of the ROI
        plus 0.5 (between grey values; see the module notes: not for an ROI that can be
        uniform).
    template : ndarray, optional
        ``uint8`` gray or BGR, for ``template_score``; no larger than the ROI, not constant.
    min_blob_area : int
        Smallest blob counted, px².
    polarity : {'dark', 'bright'}
        What a blob is, for ``blob_count``.
    canny : (float, float)
        Low and high hysteresis thresholds for ``edge_density``.

    Returns
    -------
    float

    Raises
    ------
    BadImageError
        Not a ``uint8`` gray or BGR image.
    RoiError
        ROI not inside the image, or empty.
    TemplateError
        ``template_score`` without a usable template.
    ValueError
        Unknown measure, threshold outside 0..255, bad polarity.
    """
    return measure_presence_details(
        image,
        measure=measure,
        roi=roi,
        threshold=threshold,
        template=template,
        min_blob_area=min_blob_area,
        polarity=polarity,
        canny=canny,
    ).value


def measure_presence_details(
    image: Any,
    *,
    measure: str,
    roi: Sequence[int] | None = None,
    threshold: float | None = None,
    template: Any = None,
    min_blob_area: int = 20,
    polarity: Polarity = "dark",
    canny: tuple[float, float] = (CANNY_LOW, CANNY_HIGH),
) -> PresenceResult:
    """:func:`measure_presence` (same parameters), with the threshold used and where the part
    was seen; see :class:`PresenceResult`."""
    if measure not in MEASURES:
        raise ValueError(f"measure must be one of {', '.join(MEASURES)}, not {measure!r}")
    if polarity not in ("dark", "bright"):
        raise ValueError(f"polarity must be 'dark' or 'bright', not {polarity!r}")
    if threshold is not None and not 0.0 <= float(threshold) <= 255.0:
        raise ValueError(f"threshold must be a grey level 0..255, not {threshold}")
    gray = to_gray(image)
    region, box = crop_roi(gray, roi)
    size = float(region.size)

    if measure == "mean_intensity":
        return PresenceResult(measure, float(region.mean()), box)
    if measure == "edge_density":
        low, high = float(canny[0]), float(canny[1])
        if not 0.0 <= low <= high:
            raise ValueError(f"canny thresholds must be 0 <= low <= high, not {canny}")
        edges = cv2.Canny(region, low, high)
        return PresenceResult(measure, float(np.count_nonzero(edges)) / size, box)
    if measure == "template_score":
        return _template_score(region, box, template)

    level = _otsu(region) if threshold is None else float(threshold)
    if measure == "dark_fraction":
        return PresenceResult(measure, float(np.count_nonzero(region < level)) / size, box, level)
    if measure == "bright_fraction":
        return PresenceResult(measure, float(np.count_nonzero(region > level)) / size, box, level)

    mask = (region < level) if polarity == "dark" else (region > level)
    count, _, stats, centroids = cv2.connectedComponentsWithStats(
        mask.astype(np.uint8), connectivity=8
    )
    areas = stats[1:count, cv2.CC_STAT_AREA]
    kept = [i + 1 for i in np.argsort(-areas, kind="stable") if areas[i] >= min_blob_area]
    u0, v0 = box[0], box[1]
    blobs = tuple(
        (
            u0 + int(stats[i, cv2.CC_STAT_LEFT]),
            v0 + int(stats[i, cv2.CC_STAT_TOP]),
            int(stats[i, cv2.CC_STAT_WIDTH]),
            int(stats[i, cv2.CC_STAT_HEIGHT]),
        )
        for i in kept
    )
    location = (
        (u0 + float(centroids[kept[0], 0]), v0 + float(centroids[kept[0], 1])) if kept else None
    )
    return PresenceResult(measure, float(len(kept)), box, level, location, blobs)


def _otsu(region: Gray) -> float:
    """Otsu's threshold as a level between grey values: OpenCV's ``t`` puts ``<= t`` in the dark
    class, so the level is ``t + 0.5`` and dark = ``< level``, bright = ``> level``."""
    level, _ = cv2.threshold(region, 0, 255, cv2.THRESH_BINARY | cv2.THRESH_OTSU)
    return float(level) + 0.5


def _template_score(region: Gray, box: tuple[int, int, int, int], template: Any) -> PresenceResult:
    if template is None:
        raise TemplateError("measure 'template_score' needs a template image")
    patch = to_gray(template, what="template")
    th, tw = patch.shape
    if th > region.shape[0] or tw > region.shape[1]:
        raise TemplateError(
            f"the {tw}x{th} template is larger than the {region.shape[1]}x{region.shape[0]} ROI"
        )
    if float(patch.std()) == 0.0:
        raise TemplateError("the template is constant: normalised correlation is undefined")
    scores = np.nan_to_num(
        cv2.matchTemplate(region, patch, cv2.TM_CCOEFF_NORMED), nan=0.0, posinf=0.0, neginf=0.0
    )
    y, x = np.unravel_index(int(np.argmax(scores)), scores.shape)
    location = (box[0] + float(x) + (tw - 1) / 2.0, box[1] + float(y) + (th - 1) / 2.0)
    return PresenceResult("template_score", float(min(scores[y, x], 1.0)), box, None, location)
