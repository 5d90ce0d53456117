"""Presence measures: the paper's magnet check (Figure 4) on the simulated QC camera, synthetic
present/absent cases under lighting variation, and the input checks."""

from __future__ import annotations

import math
from pathlib import Path

import cv2
import numpy as np
import pytest
from numpy.typing import NDArray

from vision_server.analysis import (
    MEASURES,
    BadImageError,
    PresenceResult,
    RoiError,
    TemplateError,
    measure_presence,
    measure_presence_details,
)

REPO = Path(__file__).resolve().parents[3]
SCENE = REPO / "examples" / "scenes" / "grundfos_cell.yaml"

# What an integrator configures for the magnet check: an ROI over the magnet's slot above the
# rotor core in the QC image (slot at about (511, 265) px; the core's rim is at v ~ 292), a
# threshold half-way between the table (~170) and the magnet (~40), and pass ranges.
QC_ROI = [481, 222, 60, 60]
QC_CHECKS: dict[str, dict[str, float]] = {
    "mean_intensity": {"max": 145.0},
    "dark_fraction": {"min": 0.15},
    "bright_fraction": {"max": 0.85},
    "edge_density": {"min": 0.01},
    "blob_count": {"min": 1},
    "template_score": {"min": 0.6},
}
THRESHOLD = 100.0
MIN_BLOB_AREA = 100


def passes(value: float, check: dict[str, float]) -> bool:
    return check.get("min", -math.inf) <= value <= check.get("max", math.inf)


# --- the simulated cell -----------------------------------------------------------------------


def _slot_pose(cell, offset_m: NDArray[np.float64], yaw: float, side: float = 1.0):
    from geometry import transform_from_xyz_rpy

    core = cell.world.part_pose("rotor_core")[:3, 3]
    z = cell.world.parts["magnet"].world_from_part[2, 3]
    xy = core[:2] + [side * 0.05, 0.0] + offset_m
    return transform_from_xyz_rpy([xy[0], xy[1], z], [0.0, 0.0, yaw])


@pytest.fixture(scope="module")
def magnet_template() -> NDArray[np.uint8]:
    """The integrator's template: the magnet's outer end, cut from one reference image."""
    from simulation import SimCell

    cell = SimCell.from_yaml(SCENE, seed=100)
    cell.world.parts["magnet"].world_from_part = _slot_pose(cell, np.zeros(2), 0.0)
    image = cell.render("qc_camera").color
    return np.ascontiguousarray(image[228:262, 490:534])


def test_magnet_check_on_simulated_qc_camera(magnet_template: NDArray[np.uint8]) -> None:
    from simulation import SimCell

    rng = np.random.default_rng(7)
    right = {m: 0 for m in MEASURES}
    cases = 0
    for seed in range(3):
        cell = SimCell.from_yaml(SCENE, seed=seed)
        feeder = cell.world.parts["magnet"].world_from_part.copy()
        for i in range(20):
            present = i % 2 == 0
            if present:  # placed, a few millimetres and degrees off nominal
                pose = _slot_pose(cell, rng.uniform(-0.002, 0.002, 2), rng.uniform(-0.1, 0.1))
            elif i % 4 == 1:  # still in the feeder
                pose = feeder
            else:  # put on the wrong side of the core
                pose = _slot_pose(cell, rng.uniform(-0.002, 0.002, 2), 0.0, side=-1.0)
            cell.world.parts["magnet"].world_from_part = pose
            frame = cell.render("qc_camera")
            u, v = frame.truth.features["magnet.top_centre"].uv
            in_roi = 0 <= u - QC_ROI[0] < QC_ROI[2] and 0 <= v - QC_ROI[1] < QC_ROI[3]
            assert in_roi == present
            cases += 1
            for measure in MEASURES:
                value = measure_presence(
                    frame.color,
                    measure=measure,
                    roi=QC_ROI,
                    threshold=THRESHOLD,
                    template=magnet_template,
                    min_blob_area=MIN_BLOB_AREA,
                )
                right[measure] += passes(value, QC_CHECKS[measure]) == present
    accuracy = {m: right[m] / cases for m in MEASURES}
    print("presence, sim QC camera:", {m: f"{a:.1%}" for m, a in accuracy.items()}, cases)
    for measure in MEASURES:
        assert accuracy[measure] >= 0.99, measure


def test_details_mark_the_magnet(magnet_template: NDArray[np.uint8]) -> None:
    from simulation import SimCell

    cell = SimCell.from_yaml(SCENE, seed=5)
    cell.world.parts["magnet"].world_from_part = _slot_pose(cell, np.zeros(2), 0.0)
    frame = cell.render("qc_camera")
    slot = frame.truth.features["magnet.top_centre"].uv
    blobs = measure_presence_details(
        frame.color, measure="blob_count", roi=QC_ROI, threshold=THRESHOLD, min_blob_area=100
    )
    assert blobs.value == 1.0
    assert blobs.threshold == THRESHOLD
    assert blobs.roi == tuple(QC_ROI)
    assert len(blobs.blobs) == 1
    u, v, w, h = blobs.blobs[0]
    assert QC_ROI[0] <= u <= slot[0] <= u + w
    assert blobs.location is not None
    assert abs(blobs.location[0] - slot[0]) < 1.0
    match = measure_presence_details(
        frame.color, measure="template_score", roi=QC_ROI, template=magnet_template
    )
    assert match.location is not None
    # The template was cut at rows 228..261, cols 490..533 of an image with the magnet here.
    assert math.hypot(match.location[0] - 511.5, match.location[1] - 244.5) < 1.5


# --- synthetic present/absent cases with lighting variation -----------------------------------


def _rectangle(
    canvas: NDArray[np.float64],
    centre: tuple[float, float],
    size: tuple[float, float],
    angle: float,
    level: float,
) -> None:
    """Paint an anti-aliased rotated rectangle (8x supersampling, area averaging)."""
    s = 8
    reach = math.hypot(*size) / 2 + 2
    u0, v0 = max(int(centre[0] - reach), 0), max(int(centre[1] - reach), 0)
    u1 = min(int(centre[0] + reach) + 1, canvas.shape[1])
    v1 = min(int(centre[1] + reach) + 1, canvas.shape[0])
    vs, us = np.mgrid[0 : (v1 - v0) * s, 0 : (u1 - u0) * s].astype(np.float64)
    x = (us + 0.5) / s - 0.5 + u0 - centre[0]
    y = (vs + 0.5) / s - 0.5 + v0 - centre[1]
    c, n = math.cos(angle), math.sin(angle)
    inside = (np.abs(c * x + n * y) <= size[0] / 2) & (np.abs(-n * x + c * y) <= size[1] / 2)
    cover = cv2.resize(inside.astype(np.float32), (u1 - u0, v1 - v0), interpolation=cv2.INTER_AREA)
    patch = canvas[v0:v1, u0:u1]
    patch += cover * (level - patch)


def synthetic_case(rng: np.random.Generator, present: bool) -> NDArray[np.uint8]:
    """A 100x100 ROI image: lit background (level, gain and gradient vary), maybe a dark part,
    specks and a faint scratch as distractors, Gaussian noise."""
    gain = rng.uniform(0.75, 1.25)
    background = rng.uniform(150.0, 200.0)
    y, x = np.mgrid[0:100, 0:100].astype(np.float64)
    direction = rng.uniform(0, 2 * np.pi)
    canvas = background + rng.uniform(0, 25) * ((x - 50) * np.cos(direction)) / 50
    canvas += 0 * y
    if present:
        centre = (50 + rng.uniform(-6, 6), 50 + rng.uniform(-6, 6))
        _rectangle(canvas, centre, (26 + rng.uniform(-2, 2), 50), rng.uniform(-0.15, 0.15), 45)
    for _ in range(rng.integers(0, 4)):  # dust: small dark specks
        u, v = rng.uniform(5, 95, 2)
        cv2.circle(canvas, (int(u), int(v)), int(rng.integers(1, 3)), float(background - 80), -1)
    if rng.uniform() < 0.5:  # a faint scratch
        p = rng.uniform(5, 95, 4).astype(int)
        cv2.line(canvas, (p[0], p[1]), (p[2], p[3]), float(background - 25), 1, cv2.LINE_AA)
    canvas = canvas * gain + rng.normal(0, rng.uniform(2.0, 3.0), canvas.shape)
    return np.clip(np.rint(canvas), 0, 255).astype(np.uint8)


SYNTHETIC_CHECKS: dict[str, dict[str, float]] = {
    "mean_intensity": {"max": 160.0},
    "dark_fraction": {"min": 0.06},
    "bright_fraction": {"max": 0.94},
    "edge_density": {"min": 0.012},
    "blob_count": {"min": 1},
    "template_score": {"min": 0.6},
}


def test_synthetic_cases_with_lighting_variation() -> None:
    rng = np.random.default_rng(11)
    template_canvas = np.full((60, 46), 175.0)
    _rectangle(template_canvas, (22.5, 29.5 + 12), (26, 50), 0.0, 45)
    template = np.clip(np.rint(template_canvas), 0, 255).astype(np.uint8)[:40]
    right = {m: 0 for m in MEASURES}
    cases = 300
    for i in range(cases):
        present = i % 2 == 0
        image = synthetic_case(rng, present)
        for measure in MEASURES:
            value = measure_presence(
                image, measure=measure, threshold=THRESHOLD, template=template, min_blob_area=50
            )
            right[measure] += passes(value, SYNTHETIC_CHECKS[measure]) == present
    accuracy = {m: right[m] / cases for m in MEASURES}
    print(
        "presence, synthetic with lighting variation:", {m: f"{a:.1%}" for m, a in accuracy.items()}
    )
    for measure in ("dark_fraction", "bright_fraction", "blob_count", "template_score"):
        assert accuracy[measure] >= 0.99, measure
    # The mean grey level cannot tell a darker table from a magnet under +-25 % gain, and
    # faint scratches add edges: no fixed range gets these right every time (reported).
    assert accuracy["mean_intensity"] >= 0.55
    assert accuracy["edge_density"] >= 0.9


# --- each measure on a known image ------------------------------------------------------------


@pytest.fixture
def half_dark() -> NDArray[np.uint8]:
    image = np.full((40, 60), 200, np.uint8)
    image[:, :20] = 50
    return image


def test_values_on_a_known_image(half_dark: NDArray[np.uint8]) -> None:
    def m(measure: str, **kw: object) -> float:
        return measure_presence(half_dark, measure=measure, **kw)  # type: ignore[arg-type]

    assert m("mean_intensity") == pytest.approx((50 * 20 + 200 * 40) / 60)
    assert m("mean_intensity", roi=[0, 0, 20, 40]) == 50.0
    assert m("dark_fraction", threshold=100) == pytest.approx(1 / 3)
    assert m("bright_fraction", threshold=100) == pytest.approx(2 / 3)
    assert m("dark_fraction") == pytest.approx(1 / 3)  # Otsu
    assert m("dark_fraction", roi=[10, 0, 20, 40], threshold=100) == pytest.approx(0.5)
    assert m("blob_count", threshold=100) == 1.0
    assert m("blob_count", threshold=100, min_blob_area=801) == 0.0
    assert m("blob_count", threshold=100, polarity="bright") == 1.0
    # One vertical edge, 40 px long, marked on one or two columns.
    assert 40 / 2400 <= m("edge_density") <= 80 / 2400
    assert m("edge_density", roi=[30, 0, 30, 40]) == 0.0
    template = half_dark[10:30, 10:30].copy()
    assert m("template_score", template=template) == pytest.approx(1.0, abs=1e-4)
    details = measure_presence_details(half_dark, measure="template_score", template=template)
    assert isinstance(details, PresenceResult)
    assert details.location is not None
    assert details.location[0] == 19.5  # the edge fixes u only


def test_bgr_equals_gray(half_dark: NDArray[np.uint8]) -> None:
    bgr = cv2.cvtColor(half_dark, cv2.COLOR_GRAY2BGR)
    for measure in ("mean_intensity", "dark_fraction", "edge_density", "blob_count"):
        assert measure_presence(bgr, measure=measure, threshold=100) == measure_presence(
            half_dark, measure=measure, threshold=100
        )


def test_errors(half_dark: NDArray[np.uint8]) -> None:
    with pytest.raises(ValueError, match="measure"):
        measure_presence(half_dark, measure="colour")
    with pytest.raises(ValueError, match="threshold"):
        measure_presence(half_dark, measure="dark_fraction", threshold=300)
    with pytest.raises(BadImageError):
        measure_presence(half_dark.astype(np.float64), measure="mean_intensity")
    with pytest.raises(BadImageError):
        measure_presence(np.zeros((0, 5), np.uint8), measure="mean_intensity")
    with pytest.raises(RoiError):
        measure_presence(half_dark, measure="mean_intensity", roi=[50, 0, 20, 10])
    with pytest.raises(RoiError):
        measure_presence(half_dark, measure="mean_intensity", roi=[0, 0, 0, 10])
    with pytest.raises(TemplateError):
        measure_presence(half_dark, measure="template_score")
    with pytest.raises(TemplateError, match="larger"):
        measure_presence(
            half_dark, measure="template_score", roi=[0, 0, 10, 10], template=half_dark[:20, :20]
        )
    with pytest.raises(TemplateError, match="constant"):
        measure_presence(half_dark, measure="template_score", template=np.zeros((5, 5), np.uint8))
