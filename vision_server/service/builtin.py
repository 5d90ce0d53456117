"""The built-in catalog a server serves when it is started without a configuration file:
one camera whose images arrive in the request, and one presence inspection on it."""

from __future__ import annotations

from dataclasses import dataclass

import cv2

from ..cameras import RequestCamera, RequestCameraSettings
from ..inspections import InspectionInput, InspectionOutcome
from .catalog import Catalog


@dataclass(frozen=True)
class MeanIntensityPresence:
    """Presence check by the mean gray level over the whole image, pass when in [low, high]."""

    name: str = "brightness"
    camera: str = "tool"
    low: float = 0.0
    high: float = 255.0
    frames: int = 1

    @property
    def type(self) -> str:
        return "presence"

    @property
    def uses_depth(self) -> bool:
        return False

    def run(self, image: InspectionInput, *, overlay: bool) -> InspectionOutcome:
        mean = float(
            cv2.mean(image.color)[0]
            if image.color.ndim == 2
            else sum(cv2.mean(image.color)[:3]) / 3.0
        )
        passed = self.low <= mean <= self.high
        data = {
            "measure": "mean_intensity",
            "value": round(mean, 4),
            "min": self.low,
            "max": self.high,
        }
        return InspectionOutcome(passed, data, image.color.copy() if overlay else None)


def builtin_catalog() -> Catalog:
    return Catalog.build(
        [RequestCamera("tool", RequestCameraSettings())],
        [MeanIntensityPresence("brightness", "tool", 64.0, 255.0)],
    )
