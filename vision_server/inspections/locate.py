"""``locate``: feature locate (template, circle, blob) → sub-pixel features, best first; passes
when at least ``min_count`` are found (the paper's vision pick, Table 1, steps 2-3)."""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from yamlfile import Node, boolean, fraction, number, one_of, positive, positive_int

from ..analysis import CENTRES, MAX_SCALE, MIN_SCALE, AnalysisError, Feature, Rejection, locate
from ..cameras import CameraSettings
from .base import (
    Common,
    Configured,
    analysis_failed,
    draw_text,
    draw_verdict,
    load_template,
    overlay_base,
    parse_common,
)
from .contract import InspectionInput, InspectionOutcome
from .kinds import Data, ResultKind, as_number, points

RED = (0, 0, 255)
ORANGE = (0, 140, 255)

MAX_REJECTED = 20
"""Most rejected circle candidates a result reports (the strongest Hough candidates first)."""


@dataclass(frozen=True)
class LocateInspection(Configured):
    common: Common
    method: str
    min_count: int
    max_count: int
    min_score: float | None
    options: Mapping[str, Any] = field(default_factory=dict)
    show_rejected: bool = False

    type = "locate"
    uses_depth = False

    def run(self, image: InspectionInput, *, overlay: bool) -> InspectionOutcome:
        kwargs: dict[str, Any] = dict(self.options)
        if self.min_score is not None:
            kwargs["min_score"] = self.min_score
        rejected: list[Rejection] = []
        if self.method == "circle":
            kwargs["rejected"] = rejected
        try:
            features = locate(
                image.color,
                method=self.method,
                roi=self.common.roi,
                max_count=self.max_count,
                **kwargs,
            )
        except AnalysisError as exc:
            raise analysis_failed(self.common.name, exc) from None
        passed = len(features) >= self.min_count
        data: dict[str, Any] = {
            "method": self.method,
            "count": len(features),
            "min_count": self.min_count,
            "features": [_feature_dict(f) for f in features],
        }
        if self.method == "circle":
            data["rejected"] = [_rejection_dict(r) for r in rejected[:MAX_REJECTED]]
        picture = None
        if overlay:
            picture = overlay_base(image.color, self.common.roi)
            if self.show_rejected:
                for rejection in rejected[:MAX_REJECTED]:
                    _draw_rejection(picture, rejection)
            for rank, feature in enumerate(features):
                _draw_feature(picture, feature, rank)
            draw_verdict(picture, passed, f"{len(features)} found")
        return InspectionOutcome(passed, data, picture)


def _feature_dict(feature: Feature) -> dict[str, Any]:
    out: dict[str, Any] = {
        "u": float(feature.u),
        "v": float(feature.v),
        "angle": float(feature.angle),
        "score": float(feature.score),
    }
    if feature.radius is not None:
        out["radius"] = float(feature.radius)
    if feature.area is not None:
        out["area"] = float(feature.area)
    if feature.scale is not None:
        out["scale"] = float(feature.scale)
    if feature.visible is not None:
        out["visible"] = float(feature.visible)
    return out


def _rejection_dict(rejection: Rejection) -> dict[str, Any]:
    return {
        "u": float(rejection.u),
        "v": float(rejection.v),
        "radius": float(rejection.radius),
        "reason": rejection.reason,
    }


def _draw_rejection(picture: Any, rejection: Rejection) -> None:
    """A rejected candidate: a thin orange circle and the start of its reason."""
    centre = (int(round(rejection.u)), int(round(rejection.v)))
    cv2.circle(picture, centre, max(int(round(rejection.radius)), 1), ORANGE, 1, cv2.LINE_8)
    reason = rejection.reason if len(rejection.reason) <= 40 else rejection.reason[:39] + "..."
    radius = int(rejection.radius)
    draw_text(picture, reason, (centre[0] - radius, centre[1] + radius + 4), ORANGE)


def _draw_feature(picture: Any, feature: Feature, rank: int) -> None:
    centre = (int(round(feature.u)), int(round(feature.v)))
    if feature.radius is not None:
        cv2.circle(picture, centre, int(round(feature.radius)), RED, 2, cv2.LINE_AA)
    cv2.drawMarker(picture, centre, RED, cv2.MARKER_CROSS, 16, 2)
    tip = (
        int(round(feature.u + 25 * np.cos(feature.angle))),
        int(round(feature.v + 25 * np.sin(feature.angle))),
    )
    if feature.angle:
        cv2.line(picture, centre, tip, RED, 1, cv2.LINE_AA)
    draw_text(picture, str(rank + 1), (centre[0] + 8, centre[1] - 8), RED)


def _threshold(value: Any) -> float | str:
    if value == "otsu":
        return "otsu"
    out = number(value)
    if not 0 <= out <= 255:
        raise ValueError(f"expected a grey level in 0..255 or 'otsu', got {value!r}")
    return out


SCORE_RANGES: dict[str, tuple[float, float, str]] = {
    "template": (-1.0, 1.0, "a normalised correlation, -1..1"),
    "circle": (0.0, 1.0, "the fraction of the outline's rays that found its edge, 0..1"),
    "blob": (0.0, math.inf, "the blob's area in pixels², >= 0"),
}
"""What ``min_score`` means for each method, and its range (docs/configuration.md)."""

MAX_POSES = 3600
"""Most poses (rotations x scales) a template search may try per request (2π in steps of
0.1°, or a tenth of that at each of ten scales)."""


def _min_score(node: Node, method: str) -> float | None:
    value = node.take("min_score", number, None)
    low, high, meaning = SCORE_RANGES[method]
    if value is not None and not low <= value <= high:
        raise node.error(
            f"min_score {value:g} is out of range for method {method}: its score is {meaning}",
            "min_score",
        )
    return value


def parse_locate(
    node: Node, base_dir: Path, cameras: Mapping[str, CameraSettings]
) -> LocateInspection:
    common = parse_common(node, "locate", cameras)
    return LocateInspection(common, *parse_locate_settings(node, base_dir, common))


LocateSettings = tuple[str, int, int, float | None, dict[str, Any], bool]
"""``(method, min_count, max_count, min_score, options, show_rejected)``."""


def parse_locate_settings(node: Node, base_dir: Path, common: Common | None) -> LocateSettings:
    """The keys of a locate after the common ones (also a job's ``locate`` step's);
    ``common`` bounds a template's size by the region searched (None: not checked)."""
    method = node.take("method", one_of("template", "circle", "blob"))
    min_count = node.take("min_count", positive_int, 1)
    max_count = node.take("max_count", positive_int, 10)
    if max_count < min_count:
        raise node.error(f"max_count ({max_count}) is below min_count ({min_count})", "max_count")
    min_score = _min_score(node, method)
    options: dict[str, Any] = {}
    for other in ("template", "circle", "blob"):
        if other != method and other in node:
            raise node.error(f"{other!r} options given, but method is {method!r}", other)
        node.take(other, lambda v: v, None)
    sub = node.sub(method, required=True)
    show_rejected = False
    if method == "template":
        options["template"] = load_template(sub, "image", base_dir, common)
        low = sub.take("angle_min", number, 0.0)
        high = sub.take("angle_max", number, 0.0)
        step = sub.take("angle_step", positive, 0.0175)
        if high < low:
            raise sub.error(f"angle_max ({high}) is below angle_min ({low})", "angle_max")
        if high - low > 2 * math.pi + 1e-9:
            raise sub.error(
                f"angle_max - angle_min is {high - low:.3f} rad, more than a full turn (2π)",
                "angle_max",
            )
        rotations = (high - low) / step + 1
        if rotations > MAX_POSES:
            raise sub.error(
                f"{rotations:.0f} rotations per request: more than {MAX_POSES} "
                f"(make angle_step larger)",
                "angle_step",
            )
        options["angle_range"] = (low, high)
        options["angle_step"] = step
        _template_scale_options(sub, options, rotations)
    elif method == "circle":
        low_r = sub.take("min_radius_px", positive)
        high_r = sub.take("max_radius_px", positive)
        if high_r < low_r:
            raise sub.error(
                f"max_radius_px ({high_r}) is below min_radius_px ({low_r})", "max_radius_px"
            )
        options["radius_range"] = (low_r, high_r)
        options["polarity"] = sub.take("polarity", one_of("bright", "dark"), "bright")
        _circle_edge_options(sub, options)
        show_rejected = sub.take("show_rejected", boolean, False)
    else:
        options["threshold"] = sub.take("threshold", _threshold, "otsu")
        options["polarity"] = sub.take("polarity", one_of("dark", "bright"), "dark")
        options["min_area"] = sub.take("min_area_px", positive, 20.0)
        options["max_area"] = sub.take("max_area_px", positive, None)
        if options["max_area"] is not None and options["max_area"] < options["min_area"]:
            raise sub.error(
                f"max_area_px ({options['max_area']:g}) is below min_area_px "
                f"({options['min_area']:g})",
                "max_area_px",
            )
        options["min_circularity"] = sub.take("min_circularity", fraction, 0.0)
    sub.finish()
    return method, min_count, max_count, min_score, options, show_rejected


def _scale(value: Any) -> float:
    out = number(value)
    if not MIN_SCALE <= out <= MAX_SCALE:
        raise ValueError(
            f"expected a scale (part size / template size) in {MIN_SCALE:g}..{MAX_SCALE:g}, "
            f"got {value!r}"
        )
    return out


def _template_scale_options(sub: Node, options: dict[str, Any], rotations: float) -> None:
    """The template search's scales (docs/configuration.md, locate.template)."""
    low = sub.take("scale_min", _scale, 1.0)
    high = sub.take("scale_max", _scale, 1.0)
    step = sub.take("scale_step", positive, 0.02)
    if high < low:
        raise sub.error(f"scale_max ({high:g}) is below scale_min ({low:g})", "scale_max")
    scales = math.floor((high - low) / step + 1e-9) + 1
    if high - (low + step * (scales - 1)) > 1e-9:
        scales += 1  # the search always tries scale_max too
    if rotations * scales > MAX_POSES:
        raise sub.error(
            f"{rotations:.0f} rotations x {scales} scales = {rotations * scales:.0f} poses per "
            f"request: more than {MAX_POSES} (make scale_step or angle_step larger)",
            "scale_step",
        )
    options["scale_range"] = (low, high)
    options["scale_step"] = step


def _edge_sigma(value: Any) -> float | None:
    if value == "auto":
        return None
    out = positive(value)
    return out


def _grey_level(value: Any) -> float:
    out = number(value)
    if not 0 < out <= 255:
        raise ValueError(f"expected a grey-level step in (0, 255], got {value!r}")
    return out


def _rays(value: Any) -> int:
    out = positive_int(value)
    if not 16 <= out <= 3600:
        raise ValueError(f"expected 16..3600 rays, got {value!r}")
    return out


def _circle_edge_options(sub: Node, options: dict[str, Any]) -> None:
    """The circle edge model's settings (docs/configuration.md, locate.circle)."""
    options["edge_sigma_px"] = sub.take("edge_sigma_px", _edge_sigma, None)
    options["max_edge_sigma_px"] = sub.take("max_edge_sigma_px", positive, 6.0)
    sigma = options["edge_sigma_px"]
    if sigma is not None and sigma > options["max_edge_sigma_px"]:
        raise sub.error(
            f"edge_sigma_px ({sigma:g}) is above max_edge_sigma_px "
            f"({options['max_edge_sigma_px']:g})",
            "edge_sigma_px",
        )
    options["min_contrast"] = sub.take("min_edge_contrast", _grey_level, 15.0)
    options["rays"] = sub.take("rays", _rays, 180)
    options["centre"] = sub.take("centre", one_of(*CENTRES), "edge")


def _locate_expected(data: Data) -> dict[str, Any]:
    return {
        "count": int(data["count"]),
        "features": points((f["u"], f["v"]) for f in data["features"]),
    }


def _locate_summary(data: Data) -> dict[str, float]:
    first = data["features"][0] if data.get("features") else {}
    return {
        "count": as_number(data, "count"),
        "u": as_number(first, "u"),
        "v": as_number(first, "v"),
    }


RESULTS = ResultKind(
    ("count", "features"),
    _locate_expected,
    _locate_summary,
    units={"count": "features", "u": "px", "v": "px"},
)
"""A locate result: how many features, where (the first one's position in the summary)."""
