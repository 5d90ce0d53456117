"""``presence``: an ROI presence check (the paper's magnet check, Table 2): one measure over
the ROI, pass when it lies in [min, max]."""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2

from yamlfile import Node, non_negative_int, number, one_of, string

from ..analysis import MEASURES, AnalysisError, Polarity, measure_presence
from ..cameras import CameraSettings
from .base import (
    Common,
    Configured,
    Image,
    analysis_failed,
    draw_verdict,
    load_template,
    overlay_base,
    parse_common,
)
from .contract import InspectionInput, InspectionOutcome
from .kinds import Data, ResultKind, as_number

MEASURE_RANGES: dict[str, tuple[float, float, str]] = {
    "mean_intensity": (0.0, 255.0, "a grey level, 0..255"),
    "dark_fraction": (0.0, 1.0, "a fraction of the ROI's pixels, 0..1"),
    "bright_fraction": (0.0, 1.0, "a fraction of the ROI's pixels, 0..1"),
    "edge_density": (0.0, 1.0, "edge pixels per ROI pixel, 0..1"),
    "blob_count": (0.0, math.inf, "a number of blobs, >= 0"),
    "template_score": (-1.0, 1.0, "a normalised correlation, -1..1"),
}
"""Each measure's values (what ``min`` and ``max`` compare with; docs/configuration.md)."""

# The keys only some measures use: a key that a measure ignores is refused, not silently
# dropped (the integrator meant something by it).
USES: dict[str, tuple[str, ...]] = {
    "threshold": ("dark_fraction", "bright_fraction", "blob_count"),
    "template": ("template_score",),
    "min_blob_area": ("blob_count",),
    "polarity": ("blob_count",),
}


@dataclass(frozen=True)
class PresenceInspection(Configured):
    common: Common
    measure: str
    low: float | None
    high: float | None
    threshold: float | None
    template: Image | None
    min_blob_area: int
    polarity: Polarity = "dark"

    type = "presence"
    uses_depth = False

    def run(self, image: InspectionInput, *, overlay: bool) -> InspectionOutcome:
        try:
            value = measure_presence(
                image.color,
                measure=self.measure,
                roi=self.common.roi,
                threshold=self.threshold,
                template=self.template,
                min_blob_area=self.min_blob_area,
                polarity=self.polarity,
            )
        except AnalysisError as exc:
            raise analysis_failed(self.common.name, exc) from None
        passed = (self.low is None or value >= self.low) and (
            self.high is None or value <= self.high
        )
        data = {"measure": self.measure, "value": value, "min": self.low, "max": self.high}
        picture = None
        if overlay:
            picture = overlay_base(image.color, self.common.roi)
            draw_verdict(picture, passed, f"{self.measure} = {value:.3f}")
            if not passed and self.common.roi is not None:
                u, v, w, h = self.common.roi
                cv2.rectangle(picture, (u, v), (u + w - 1, v + h - 1), (0, 0, 255), 2)
        return InspectionOutcome(passed, data, picture)


def parse_presence(
    node: Node, base_dir: Path, cameras: Mapping[str, CameraSettings]
) -> PresenceInspection:
    common = parse_common(node, "presence", cameras)
    return PresenceInspection(common, *parse_presence_settings(node, base_dir, common))


PresenceSettings = tuple[str, float | None, float | None, float | None, Image | None, int, Polarity]
"""``(measure, min, max, threshold, template, min_blob_area, polarity)``."""


def parse_presence_settings(node: Node, base_dir: Path, common: Common | None) -> PresenceSettings:
    """The keys of a presence check after the common ones (also a job's ``presence`` step's);
    ``common`` bounds a template's size by the ROI (None: not checked)."""
    measure = node.take("measure", one_of(*MEASURES))
    for key, measures in USES.items():
        if node.has(key) and measure not in measures:
            raise node.error(
                f"{key} is not used by measure {measure} (only by {', '.join(measures)})", key
            )
    low = node.take("min", number, None)
    high = node.take("max", number, None)
    if low is None and high is None:
        raise node.error("a presence check needs min, max or both (the pass range)")
    bottom, top, meaning = MEASURE_RANGES[measure]
    for key, value in (("min", low), ("max", high)):
        if value is not None and not bottom <= value <= top:
            raise node.error(
                f"{key} {value:g} is out of range for measure {measure}: its value is {meaning}",
                key,
            )
    if low is not None and high is not None and low > high:
        raise node.error(f"min ({low}) is above max ({high})", "min")
    template = None
    if node.has("template"):
        template = load_template(node, "template", base_dir, common)
    else:
        node.take("template", string, None)  # an allowed key
    if measure == "template_score" and template is None:
        raise node.error("measure template_score needs a template image", "measure")
    threshold = node.take("threshold", number, None)
    if threshold is not None and not 0 <= threshold <= 255:
        raise node.error(f"expected a grey level in 0..255, got {threshold}", "threshold")
    return (
        measure,
        low,
        high,
        threshold,
        template,
        node.take("min_blob_area", non_negative_int, 20),
        node.take("polarity", _polarity, "dark"),
    )


def _polarity(value: object) -> Polarity:
    """What ``blob_count`` counts: ``dark`` blobs (< threshold) or ``bright`` ones."""
    return "bright" if one_of("dark", "bright")(value) == "bright" else "dark"


def _presence_expected(data: Data) -> dict[str, Any]:
    return {"value": round(float(data["value"]), 4)}


def _presence_summary(data: Data) -> dict[str, float]:
    return {"value": as_number(data, "value")}


RESULTS = ResultKind(
    ("value",), _presence_expected, _presence_summary, units={"value": "of the measure"}
)
"""A presence result: the measured value."""
