"""ROI presence measurements (like the paper's magnet check): the server compares the value
with the inspection's ``[min, max]``."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Literal

import cv2
import numpy as np
from numpy.typing import NDArray

from vision_server.vision._checks import Roi, as_gray, check_roi, crop
from vision_server.vision.errors import ParameterError
from vision_server.vision.locate import Feature, Polarity, locate_blobs, locate_template

__all__ = ["MEASURES", "PresenceMeasurement", "measure_presence"]

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


@dataclass(frozen=True)
class PresenceMeasurement:
    """One measurement over an ROI.

    Attributes
    ----------
    measure : str
        Which measurement (one of :data:`MEASURES`).
    value : float
        ``mean_intensity``: grey level 0..255; ``dark_fraction`` / ``bright_fraction``: share
        of ROI pixels below / above ``threshold`` (0..1); ``edge_density``: Canny edge pixels
        per ROI pixel (0..1); ``blob_count``: number of blobs; ``template_score``: the best
        normalised cross-correlation in the ROI (-1..1).
    roi : (u, v, width, height)
        The ROI measured, full-image pixels.
    detections : tuple of Feature
        What was found (blobs or the template match), for the overlay.
    """

    measure: str
    value: float
    roi: Roi
    detections: tuple[Feature, ...] = ()


def measure_presence(
    image: NDArray[np.uint8],
    *,
    measure: Measure,
    roi: Sequence[float] | None = None,
    threshold: float = 128.0,
    canny: tuple[float, float] = (50.0, 150.0),
    polarity: Polarity = "dark",
    area_range: tuple[float, float] = (10.0, float("inf")),
    template: NDArray[np.uint8] | None = None,
) -> PresenceMeasurement:
    """Measure ``measure`` over the ``roi`` of a gray or BGR uint8 ``image``.

    Parameters
    ----------
    threshold : float
        Grey level for ``dark_fraction``, ``bright_fraction`` and ``blob_count``.
    canny : (float, float)
        Low and high hysteresis thresholds of ``cv2.Canny`` for ``edge_density``.
    polarity, area_range : str, (float, float)
        Blob polarity and accepted blob areas (pixels) for ``blob_count``.
    template : uint8 ndarray, optional
        Needed by ``template_score``.
    """
    gray = as_gray(image)
    box = check_roi(roi, gray.shape)
    region = np.asarray(crop(gray, box), dtype=np.uint8)
    if not 0 <= threshold <= 255:
        raise ParameterError(f"threshold must be in 0..255, got {threshold!r}")
    detections: tuple[Feature, ...] = ()
    if measure == "mean_intensity":
        value = float(region.mean())
    elif measure == "dark_fraction":
        value = float(np.mean(region < threshold))
    elif measure == "bright_fraction":
        value = float(np.mean(region > threshold))
    elif measure == "edge_density":
        edges = cv2.Canny(np.ascontiguousarray(region), float(canny[0]), float(canny[1]))
        value = float(np.count_nonzero(edges)) / region.size
    elif measure == "blob_count":
        detections = locate_blobs(
            gray, roi=box, threshold=threshold, polarity=polarity, area_range=area_range
        )
        value = float(len(detections))
    elif measure == "template_score":
        detections = locate_template(gray, template, roi=box, min_score=-1.0, max_count=1)
        value = detections[0].score if detections else -1.0
    else:
        raise ParameterError(f"measure must be one of {MEASURES}, got {measure!r}")
    return PresenceMeasurement(measure=measure, value=value, roi=box, detections=detections)
