"""``anomaly``: is this part unlike the good parts a model was trained on?

The inspection scores its ROI (the whole image without one) with a model trained from good
images only (:mod:`vision_server.analysis.anomaly`, ``vision-server train``), and passes when
the score is at most the threshold: the model's own, set at training from held-out good images
for a stated false-reject rate, or the configuration's ``threshold:``. The overlay shows the heat
map over the ROI. A job's ``anomaly`` step does the same on a fixtured ROI.

``model:`` names the model file relative to the configuration's folder. Training writes a new
file for every version and points ``model:`` at it, so the configuration's text, and with it the
configuration hash that every RESULT carries, changes with the model. A configuration whose
``model:`` file is missing still loads (the inspection can be trained); running it fails with
INSPECTION_FAILED saying so.
"""

from __future__ import annotations

import math
import threading
from collections import OrderedDict
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from protocol import InspectionFailed
from yamlfile import Node, non_negative, one_of, string

from ..analysis import (
    ANOMALY_METHODS,
    AnalysisError,
    AnomalyError,
    AnomalyModel,
    AnomalyScore,
    load_model,
)
from ..cameras import CameraSettings
from .base import (
    GREEN,
    RED,
    Common,
    Configured,
    Image,
    analysis_failed,
    crop,
    draw_verdict,
    overlay_base,
    parse_common,
    resolve,
)
from .contract import InspectionInput, InspectionOutcome
from .kinds import Data, ResultKind, as_number

HEAT_ALPHA = 0.45
"""How much of the heat map's colour an overlay mixes into the ROI."""


@dataclass(frozen=True)
class AnomalySettings:
    """The keys of an anomaly check: ``model_file`` as written (None: not trained yet),
    ``model`` the loaded model (None when the file is absent), ``threshold`` the configuration's
    override (None: the model's), and what training uses: ``method``, ``false_reject``."""

    model_file: str | None
    model: AnomalyModel | None
    threshold: float | None
    method: str
    false_reject: float

    @property
    def limit(self) -> float | None:
        """The threshold in force (None: no model)."""
        if self.threshold is not None:
            return self.threshold
        return None if self.model is None else self.model.threshold

    def judge(
        self, owner: str, patch: Image, *, job: str | None = None
    ) -> tuple[bool, dict[str, Any], AnomalyScore]:
        """Score ``patch`` (the ROI's pixels); the verdict and the RESULT's data. ``job``: the
        job whose step ``owner`` is (None: ``owner`` is an inspection). Raises the protocol
        error for an untrained inspection or an image the model cannot take."""
        if self.model is None:
            # A step is trained through its job: the command names the job and the step.
            what, command = (
                (f"inspection {owner!r}", owner)
                if job is None
                else (f"step {owner!r} of {job!r}", f"{job} --step {owner}")
            )
            raise InspectionFailed(
                f"{what} has no trained model"
                + (f" ({self.model_file} is missing)" if self.model_file else "")
                + f": train it with vision-server train {command} --config CONFIG "
                "--images 'good/*.png' (or from the console's Train panel)"
            )
        try:
            scored = self.model.score(np.ascontiguousarray(patch))
        except AnalysisError as exc:
            raise analysis_failed(owner, exc) from None
        limit = self.limit
        assert limit is not None
        if not math.isfinite(scored.score):
            raise InspectionFailed(f"{owner!r}: the model gave no finite score (a damaged model?)")
        passed = scored.score <= limit
        data = {
            "score": round(scored.score, 6),
            "threshold": round(limit, 6),
            "method": self.model.method,
            "model_version": self.model.version,
            "model_sha256": self.model.digest[:16],
        }
        return passed, data, scored


def parse_anomaly_settings(node: Node, base_dir: Path) -> AnomalySettings:
    """``model``, ``threshold``, ``method`` and ``false_reject`` (also a job step's)."""
    written = node.take("model", string, None)
    model = None
    if written is not None:
        path = resolve(base_dir, written)
        if path.is_file():
            try:
                model = cached_model(path)
            except AnomalyError as exc:
                raise node.error(str(exc), "model") from None
    threshold = node.take("threshold", non_negative, None)
    method = node.take("method", one_of(*ANOMALY_METHODS), None)
    if method is None:
        method = model.method if model is not None else "patches"
    false_reject = node.take("false_reject", non_negative, 0.01)
    if not 0.0 < false_reject < 0.5:
        raise node.error(f"expected a rate in (0, 0.5), got {false_reject}", "false_reject")
    return AnomalySettings(written, model, threshold, method, false_reject)


_CACHE: OrderedDict[tuple[str, int, int], AnomalyModel] = OrderedDict()
_CACHE_LOCK = threading.Lock()
CACHED_MODELS = 16


def cached_model(path: Path) -> AnomalyModel:
    """The model in ``path``, read once per file version (a configuration is parsed on every
    reload, try and preview; the model files are megabytes)."""
    try:
        stat = path.stat()
    except OSError as exc:
        raise AnomalyError(f"cannot read the model {path.name}: {exc.strerror}") from None
    key = (str(path.resolve()), stat.st_mtime_ns, stat.st_size)
    with _CACHE_LOCK:
        if key in _CACHE:
            _CACHE.move_to_end(key)
            return _CACHE[key]
    model = load_model(path)
    with _CACHE_LOCK:
        _CACHE[key] = model
        while len(_CACHE) > CACHED_MODELS:
            _CACHE.popitem(last=False)
    return model


def blend_heat(canvas: Image, heat: Image, to_image: Any, limit: float) -> None:
    """Blend a heat map (in score units) into the BGR ``canvas``: blue at 0, red at ``limit``
    and above. ``to_image``: the 2x3 matrix from the map's pixels to the canvas's."""
    level = np.clip(heat / max(limit, 1e-9) * 255.0, 0, 255).astype(np.uint8)
    colours = cv2.applyColorMap(level, cv2.COLORMAP_JET)
    size = (canvas.shape[1], canvas.shape[0])
    matrix = np.asarray(to_image, np.float64)
    warped = cv2.warpAffine(colours, matrix, size, flags=cv2.INTER_LINEAR)
    mask = cv2.warpAffine(np.full(heat.shape[:2], 255, np.uint8), matrix, size) > 127
    mixed = cv2.addWeighted(canvas, 1.0 - HEAT_ALPHA, warped, HEAT_ALPHA, 0.0)
    canvas[mask] = mixed[mask]


@dataclass(frozen=True)
class AnomalyInspection(Configured):
    common: Common
    settings: AnomalySettings

    type = "anomaly"
    uses_depth = False

    def run(self, image: InspectionInput, *, overlay: bool) -> InspectionOutcome:
        patch, origin = crop(image.color, self.common.roi, inspection=self.common.name)
        passed, data, scored = self.settings.judge(self.common.name, patch)
        picture = None
        if overlay:
            picture = overlay_base(image.color, None)
            if self.common.roi is not None:
                u, v, w, h = self.common.roi
                colour = GREEN if passed else RED
                cv2.rectangle(picture, (u, v), (u + w - 1, v + h - 1), colour, 2)
            shift = np.array([[1.0, 0.0, origin[0]], [0.0, 1.0, origin[1]]])
            blend_heat(picture, scored.heat, shift, data["threshold"])
            draw_verdict(picture, passed, f"anomaly {data['score']:.3g} / {data['threshold']:.3g}")
        return InspectionOutcome(passed, data, picture)


def parse_anomaly(
    node: Node, base_dir: Path, cameras: Mapping[str, CameraSettings]
) -> AnomalyInspection:
    common = parse_common(node, "anomaly", cameras)
    settings = parse_anomaly_settings(node, base_dir)
    model = settings.model
    region = common.region_size()
    if model is not None and region is not None and region != model.image_size:
        raise node.error(
            f"the model {settings.model_file} was trained on {model.image_size[0]}x"
            f"{model.image_size[1]} images; this inspection's "
            f"{'ROI' if common.roi else 'image'} is {region[0]}x{region[1]}: retrain it",
            "model",
        )
    return AnomalyInspection(common, settings)


def _anomaly_expected(data: Data) -> dict[str, Any]:
    # A golden case holds an anomaly result to its verdict: the score is in the model's own
    # units (another model, another scale) and the golden runner compares no ``score`` key.
    return {}


def _anomaly_summary(data: Data) -> dict[str, float]:
    return {"score": as_number(data, "score"), "threshold": as_number(data, "threshold")}


RESULTS = ResultKind(
    (),
    _anomaly_expected,
    _anomaly_summary,
    units={"score": "model units", "threshold": "model units"},
)
"""An anomaly result: the score and the threshold it was judged by."""

__all__ = [
    "AnomalyInspection",
    "AnomalySettings",
    "RESULTS",
    "cached_model",
    "blend_heat",
    "parse_anomaly",
    "parse_anomaly_settings",
]
