"""The ``anomaly`` step of a job: the anomaly check of ``type: anomaly`` on the step's ROI, in a
fixture's part frame when it has one, so that the model judges the part located and aligned
(train it on the same region: ``vision-server train JOB --step NAME``).

Values: ``passed``, ``score`` and ``threshold`` (``surface.score < 0.8`` in a verdict).
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass

from yamlfile import Node

from ..anomaly import AnomalySettings, parse_anomaly_settings
from .expression import ValueType
from .frame import Image
from .step import Chain, Outcome, Region, Shape, Step


@dataclass(frozen=True)
class AnomalyStep(Step):
    settings: AnomalySettings | None = None
    job: str = ""
    """The job's name (what ``vision-server train`` is given for this step)."""

    type = "anomaly"

    def produces(self) -> dict[str, ValueType]:
        return {"passed": "bool", "score": "number", "threshold": "number"}

    def patch(self, image: Image, earlier: Mapping[str, Outcome]) -> Region:
        """The pixels the model judges: the ROI, or the ROI sampled in the fixture's frame."""
        region = self.region(image, earlier)
        if region.roi is None:
            return region
        u, v, w, h = region.roi
        return Region(
            region.image[v : v + h, u : u + w], None, region.to_image, False, region.outline
        )

    def run(self, image: Image, earlier: Mapping[str, Outcome]) -> Outcome:
        assert self.settings is not None
        region = self.patch(image, earlier)
        passed, data, scored = self.settings.judge(self.name, region.image, job=self.job)
        to_image = region.to_image
        if self.fixture is None and self.roi is not None:
            to_image = to_image.copy()
            to_image[:, 2] += (self.roi[0], self.roi[1])
        shapes = [Shape("polygon", region.outline)] if region.outline else []
        values = {"passed": passed, "score": data["score"], "threshold": data["threshold"]}
        detail = {k: data[k] for k in ("method", "model_version", "model_sha256")}
        return Outcome(
            passed,
            values,
            detail,
            shapes,
            label=f"anomaly {data['score']:.3g} / {data['threshold']:.3g}",
            heat=(scored.heat, to_image, float(data["threshold"])),
        )


def parse_anomaly_step(node: Node, head: Step, chain: Chain) -> Step:
    if head.fixture is not None and head.roi is None:
        raise node.error("an anomaly step in a fixture's frame needs its roi", "roi")
    settings = parse_anomaly_settings(node, chain.base_dir)
    model = settings.model
    if model is not None and head.roi is not None and model.image_size != head.roi[2:]:
        raise node.error(
            f"the model {settings.model_file} was trained on {model.image_size[0]}x"
            f"{model.image_size[1]} images; this step's ROI is {head.roi[2]}x{head.roi[3]}: "
            "retrain it",
            "model",
        )
    return AnomalyStep(head.name, head.fixture, head.roi, settings, chain.common.name)


__all__ = ["AnomalyStep", "parse_anomaly_step"]
