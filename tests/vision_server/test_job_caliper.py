"""A job's ``caliper`` step: a width measured in the part frame of a fixture follows a plate
that moved and turned (the same band fixed in the image measures something else), its values
are the verdict's by measurement name, the overlay draws the band where the fixture put it, and
the validator names a value the step does not give, with file, line and key path."""

from __future__ import annotations

import math
from pathlib import Path

import cv2
import numpy as np
import pytest

from vision_server import InspectionInput
from vision_server.config import ConfigError, load_config
from vision_server.inspections import JobInspection

ROOT = Path(__file__).resolve().parents[2]
PLATES = ROOT / "test_inspections" / "fixtured_plate" / "images"

HEAD = """\
cameras:
  qc: {source: request}
inspections:
  - name: plate
    type: job
    camera: qc
    steps:
      - name: big_hole
        type: locate
        method: circle
        circle: {min_radius_px: 10, max_radius_px: 15, polarity: dark}
        max_count: 1
      - name: near
        type: fixture
        origin: big_hole
      - name: small_hole
        type: locate
        fixture: near
        roi: [60, -50, 80, 100]
        method: circle
        circle: {min_radius_px: 5, max_radius_px: 9, polarity: dark}
        max_count: 1
      - name: part
        type: fixture
        origin: big_hole
        x_towards: small_hole
"""
# The plate is 80 px wide across its x axis (drawn about 80.4); the band crosses it at x = 75.
GAUGE = """\
      - name: gauge
        type: caliper
        fixture: part
        measurements:
          - name: plate_width
            kind: width
            band: {center: [75, 0], length: 100, width: 6, angle_rad: 1.5707963}
            min: 79
            max: 81
"""
# The same band where the plate lies when taught (big hole at (110, 120), angle 0).
GAUGE_FIXED = GAUGE.replace("        fixture: part\n", "").replace("[75, 0]", "[185, 120]")
BAND_ENDS_PART = [(75.0, -50.0), (75.0, 50.0)]
"""The band's centre line ends in the part frame (px): where the overlay must draw it."""


def job(tmp_path: Path, steps: str, verdict: str | None = None) -> JobInspection:
    text = HEAD + steps + (f"    verdict: {verdict}\n" if verdict else "")
    (tmp_path / "cell.yaml").write_text(text, encoding="utf-8")
    (inspection,) = load_config(tmp_path / "cell.yaml").inspections
    assert isinstance(inspection, JobInspection)
    return inspection


def plate(name: str) -> np.ndarray:
    image = cv2.imread(str(PLATES / name), cv2.IMREAD_GRAYSCALE)
    assert image is not None, name
    return image


@pytest.mark.parametrize("name", ["moved_a.png", "moved_b.png"])
def test_the_width_follows_a_moved_and_turned_plate(tmp_path: Path, name: str) -> None:
    fixtured = job(tmp_path, GAUGE, "part and gauge.plate_width > 79.5")
    fixed = job(tmp_path, GAUGE_FIXED)
    for inspection in (fixtured, fixed):
        taught = inspection.run(InspectionInput(plate("taught.png")), overlay=False)
        assert taught.passed, taught.data["steps"]["gauge"]
        assert taught.data["steps"]["gauge"]["plate_width"] == pytest.approx(80.4, abs=0.2)
    moved = fixtured.run(InspectionInput(plate(name)), overlay=False)
    assert moved.passed, moved.data["steps"]["gauge"]
    gauge = moved.data["steps"]["gauge"]
    assert gauge["plate_width"] == pytest.approx(80.4, abs=0.2)
    assert gauge["failed"] == 0
    assert gauge["units"] == "px"
    (record,) = gauge["measurements"]
    assert (record["name"], record["unit"], record["kind"]) == ("plate_width", "px", "width")
    stuck = fixed.run(InspectionInput(plate(name)), overlay=False)
    assert not stuck.passed
    assert stuck.data["failed"] == ["gauge"]


def test_a_narrow_plate_fails_the_caliper_step_alone_in_millimetres(tmp_path: Path) -> None:
    steps = (
        GAUGE.replace(
            "        measurements:",
            "        units: mm\n        mm_per_px: 0.1\n        measurements:",
        )
        .replace("min: 79", "min: 7.9")
        .replace("max: 81", "max: 8.1")
    )
    inspection = job(tmp_path, steps, "all(part, gauge) and gauge.plate_width >= 7.9")
    narrow = inspection.run(InspectionInput(plate("moved_narrow.png")), overlay=False)
    assert not narrow.passed
    assert narrow.data["failed"] == ["gauge"]
    gauge = narrow.data["steps"]["gauge"]
    assert gauge["plate_width"] == pytest.approx(7.44, abs=0.03)  # 74 px drawn about 74.4
    assert gauge["units"] == "mm"
    assert gauge["measurements"][0]["unit"] == "mm"
    good = inspection.run(InspectionInput(plate("moved_c.png")), overlay=False)
    assert good.passed, good.data["steps"]["gauge"]


def test_without_its_fixture_the_step_fails_with_the_reason(tmp_path: Path) -> None:
    outcome = job(tmp_path, GAUGE).run(InspectionInput(plate("no_plate.png")), overlay=False)
    assert outcome.data["steps"]["gauge"] == {
        "type": "caliper",
        "passed": False,
        "failed": None,
        "plate_width": None,
        "reason": "fixture 'part' was not made",
    }


def _greenest(overlay: np.ndarray, point: tuple[float, float]) -> int:
    """How green the overlay is within 1 px of ``point`` (u, v): green minus red, max."""
    u, v = int(round(point[0])), int(round(point[1]))
    patch = overlay[v - 1 : v + 2, u - 1 : u + 2].astype(int)
    return int((patch[..., 1] - patch[..., 2]).max())


def test_the_overlay_draws_the_band_where_the_fixture_put_it(tmp_path: Path) -> None:
    outcome = job(tmp_path, GAUGE).run(InspectionInput(plate("moved_b.png")), overlay=True)
    assert outcome.overlay is not None
    frame = outcome.data["features"][-1]
    c, s = math.cos(frame["angle"]), math.sin(frame["angle"])
    # the band's short sides (3 px either side of its centre line's ends), in image pixels
    for x, y in BAND_ENDS_PART:
        moved = (frame["u"] + c * x - s * y, frame["v"] + s * x + c * y)
        assert _greenest(outcome.overlay, moved) > 100, moved
    # nothing drawn where the band was taught (the plate turned 24 deg away from there)
    taught = (110.0 + 75.0, 120.0 - 50.0)
    assert _greenest(outcome.overlay, taught) < 50


@pytest.mark.parametrize(
    ("steps", "verdict", "marker", "path", "reason"),
    [
        (
            GAUGE,
            "gauge.width > 79",
            "verdict:",
            "-> verdict",
            "step 'gauge' has no value 'width'",
        ),
        (
            GAUGE.replace("name: plate_width", "name: plate-width"),
            None,
            "name: plate-width",
            "steps[4] (name='gauge') -> measurements[0] (name='plate-width') -> name",
            "a verdict reads it as step.name",
        ),
        (
            GAUGE.replace("name: plate_width", "name: failed"),
            None,
            "name: failed",
            "measurements[0] (name='failed') -> name",
            "cannot be named 'failed'",
        ),
        (
            GAUGE.replace("fixture: part\n", "fixture: part\n        roi: [0, 0, 10, 10]\n"),
            None,
            "roi: [0, 0",
            "steps[4] (name='gauge') -> roi",
            "it has no roi",
        ),
    ],
)
def test_the_validator_names_a_bad_caliper_step_with_file_line_and_key(
    tmp_path: Path, steps: str, verdict: str | None, marker: str, path: str, reason: str
) -> None:
    with pytest.raises(ConfigError) as info:
        job(tmp_path, steps, verdict)
    error = info.value
    text = (tmp_path / "cell.yaml").read_text(encoding="utf-8").splitlines()
    line = max(number for number, row in enumerate(text, start=1) if marker in row)
    assert error.source == "cell.yaml"
    assert error.line == line, str(error)
    assert path in error.path, str(error)
    assert reason in error.reason, str(error)


def test_a_band_the_part_moves_out_of_the_image_fails_the_step_not_the_job(
    tmp_path: Path,
) -> None:
    far = GAUGE.replace("[75, 0]", "[300, 0]")
    outcome = job(tmp_path, far).run(InspectionInput(plate("taught.png")), overlay=False)
    assert outcome.data["failed"] == ["gauge"]
    reason = outcome.data["steps"]["gauge"]["reason"]
    assert reason.startswith("a measurement in fixture 'part''s frame leaves the image: "), reason
