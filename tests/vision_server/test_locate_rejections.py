"""A circle locate says why it rejected each Hough candidate: in the result's data and, when
``show_rejected`` is set, on the overlay; its edge settings come from the YAML."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
from numpy.typing import NDArray

from vision_server import InspectionInput
from vision_server.config import load_config
from vision_server.inspections import LocateInspection

CELL = """\
cameras:
  tool:
    source: request
inspections:
  - name: caps
    type: locate
    camera: tool
    method: circle
    circle: {{min_radius_px: 20, max_radius_px: 45, min_edge_contrast: {contrast}, rays: 120,
              show_rejected: {show}}}
"""


def load(tmp_path: Path, *, contrast: float, show: bool) -> LocateInspection:
    path = tmp_path / "cell.yaml"
    path.write_text(CELL.format(contrast=contrast, show=str(show).lower()), encoding="utf-8")
    inspection = load_config(path).inspections[0]
    assert isinstance(inspection, LocateInspection)
    return inspection


def scene() -> NDArray[np.uint8]:
    """A disc (r 30) and a square (side 60) on a dark ground, blurred 2 px."""
    image = np.full((240, 320), 40.0, np.float32)
    cv2.circle(image, (90, 120), 30, 200.0, -1, cv2.LINE_AA)
    image[90:150, 190:250] = 200.0
    blurred = cv2.GaussianBlur(image, (0, 0), 2.0)
    return np.asarray(np.clip(np.rint(blurred), 0, 255), np.uint8)


def test_the_settings_reach_the_locate(tmp_path: Path) -> None:
    inspection = load(tmp_path, contrast=20, show=False)
    assert inspection.options["min_contrast"] == 20
    assert inspection.options["rays"] == 120
    assert inspection.options["edge_sigma_px"] is None  # auto
    assert inspection.options["max_edge_sigma_px"] == 6.0
    assert inspection.options["centre"] == "edge"


def test_a_rejected_candidate_is_reported_with_its_reason(tmp_path: Path) -> None:
    inspection = load(tmp_path, contrast=250, show=False)
    outcome = inspection.run(InspectionInput(scene()), overlay=False)
    # An edge step no part here reaches: the disc is seen but refused, and the data says so.
    assert outcome.data["count"] == 0
    reasons = [r["reason"] for r in outcome.data["rejected"]]
    assert any("contrast below 250 grey levels" in reason for reason in reasons), reasons
    near_disc = [r for r in outcome.data["rejected"] if abs(r["u"] - 90) < 5]
    assert near_disc
    assert abs(near_disc[0]["v"] - 120) < 5


def test_the_overlay_shows_rejections_only_when_asked(tmp_path: Path) -> None:
    image = scene()
    plain = load(tmp_path, contrast=250, show=False).run(InspectionInput(image), overlay=True)
    shown = load(tmp_path, contrast=250, show=True).run(InspectionInput(image), overlay=True)
    assert plain.overlay is not None
    assert shown.overlay is not None
    orange = np.all(shown.overlay == (0, 140, 255), axis=-1).sum()
    assert orange > 50
    assert np.all(plain.overlay == (0, 140, 255), axis=-1).sum() == 0


def test_a_found_disc_is_not_in_rejected(tmp_path: Path) -> None:
    outcome = load(tmp_path, contrast=20, show=False).run(InspectionInput(scene()), overlay=False)
    assert outcome.data["count"] == 1
    feature = outcome.data["features"][0]
    assert abs(feature["u"] - 90) < 0.2
    assert abs(feature["v"] - 120) < 0.2
    assert all(
        abs(r["u"] - 90) > 5 or "same circle" in r["reason"] for r in outcome.data["rejected"]
    )
