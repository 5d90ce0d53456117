"""``type: anomaly`` and a job's ``anomaly`` step, trained through the service's training
(vision_server.service.training) on whole camera images of seeded synthetic parts
(tests/helpers/anomaly_synthetic.py).

An untrained inspection loads and fails to run with INSPECTION_FAILED naming ``vision-server
train``; trained, a good part passes and a defective one fails with score, threshold, method,
model version and model hash in the RESULT; the configuration's threshold overrides the model's;
an ROI of another size than the model's is a configuration error naming both sizes; the overlay
blends the heat map into the ROI and nowhere else; the configuration hash changes with the model.
In a job, the step judges the part located and aligned by a fixture: trained on parts placed
anywhere, a moved and turned good part passes and a defective one fails."""

from __future__ import annotations

import hashlib
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pytest
from anomaly_synthetic import (
    DEFECTS,
    PLATE_WINDOW,
    SIZE,
    defective_part,
    good_part,
    placed_plate,
)
from numpy.typing import NDArray

from protocol import CellvisionError, InspectionFailed
from vision_server import InspectionInput
from vision_server.config import ConfigError, load_config
from vision_server.inspections import RESULT_KINDS, AnomalyInspection, JobInspection
from vision_server.inspections.base import draw_verdict, overlay_base
from vision_server.service import train_inspection, training_patches

ROI = (16, 8, SIZE, SIZE)
SCENE = (300, 260)
"""The camera image (width, height) px: the part fills the ROI, a dark belt around it."""

CONFIG = f"""\
# a comment that training keeps
cameras:
  cam: {{source: request}}
inspections:
  - name: surface
    type: anomaly   # the plate's top face
    camera: cam
    roi: [{ROI[0]}, {ROI[1]}, {ROI[2]}, {ROI[3]}]
    method: variation
"""


def scene(part: NDArray[np.uint8]) -> NDArray[np.uint8]:
    """A whole camera image with ``part`` in the ROI."""
    width, height = SCENE
    image = np.full((height, width, 3), 50, np.uint8)
    u, v, w, h = ROI
    image[v : v + h, u : u + w] = part
    return image


@dataclass
class Cell:
    folder: Path
    before: str
    after: str
    hash_before: str
    hash_after: str
    inspection: AnomalyInspection
    good: list[NDArray[np.uint8]]
    bad: list[tuple[str, NDArray[np.uint8], NDArray[np.bool_]]]


@pytest.fixture(scope="module")
def cell(tmp_path_factory: pytest.TempPathFactory) -> Cell:
    folder = tmp_path_factory.mktemp("anomaly_cell")
    path = folder / "cell.yaml"
    path.write_text(CONFIG, encoding="utf-8")
    config = load_config(path)
    rng = np.random.default_rng(8)
    images = [scene(good_part(rng)) for _ in range(16)]
    trained = train_inspection(config, CONFIG, "surface", images)
    path.write_text(trained.text, encoding="utf-8")
    after = load_config(path)
    (inspection,) = after.inspections
    assert isinstance(inspection, AnomalyInspection)
    good = [scene(good_part(rng)) for _ in range(4)]
    bad = []
    for kind in DEFECTS:
        part, mask = defective_part(rng, kind)
        whole = np.zeros(scene(part).shape[:2], bool)
        whole[ROI[1] : ROI[1] + SIZE, ROI[0] : ROI[0] + SIZE] = mask
        bad.append((kind, scene(part), whole))
    return Cell(
        folder,
        CONFIG,
        trained.text,
        config.config_hash,
        after.config_hash,
        inspection,
        good,
        bad,
    )


def write(folder: Path, text: str, name: str = "other.yaml") -> Path:
    path = folder / name
    path.write_text(text, encoding="utf-8")
    return path


def test_an_untrained_inspection_loads_and_running_it_says_how_to_train(tmp_path: Path) -> None:
    (inspection,) = load_config(write(tmp_path, CONFIG)).inspections
    assert isinstance(inspection, AnomalyInspection)
    assert inspection.settings.model is None
    assert inspection.settings.limit is None
    image = InspectionInput(scene(good_part(np.random.default_rng(0))))
    with pytest.raises(
        InspectionFailed, match="vision-server train surface --config CONFIG --images"
    ) as caught:
        inspection.run(image, overlay=False)
    assert "no trained model" in caught.value.message
    missing = CONFIG.replace("method: variation", 'model: "models/surface.v9.npz"')
    (inspection,) = load_config(write(tmp_path, missing)).inspections
    with pytest.raises(InspectionFailed, match=r"models/surface\.v9\.npz is missing"):
        inspection.run(image, overlay=False)


def test_training_writes_the_model_and_points_model_at_it(cell: Cell) -> None:
    assert (cell.folder / "models" / "surface.v1.npz").is_file()
    assert 'model: "models/surface.v1.npz"' in cell.after
    assert cell.after.startswith("# a comment that training keeps\n")
    assert "type: anomaly   # the plate's top face" in cell.after
    assert cell.after.replace('    model: "models/surface.v1.npz"\n', "") == cell.before


def test_the_configuration_hash_changes_with_the_model(cell: Cell) -> None:
    assert cell.hash_before != cell.hash_after
    # A second training writes v2: the text, and so the hash, changes again.
    path = cell.folder / "second.yaml"
    path.write_text(cell.after, encoding="utf-8")
    config = load_config(path)
    rng = np.random.default_rng(9)
    images = [scene(good_part(rng)) for _ in range(10)]
    trained = train_inspection(config, cell.after, "surface", images)
    assert trained.relative == "models/surface.v2.npz"
    assert trained.model.version == 2
    assert 'model: "models/surface.v2.npz"' in trained.text
    assert "surface.v1.npz" not in trained.text
    path.write_text(trained.text, encoding="utf-8")
    assert load_config(path).config_hash not in (cell.hash_before, cell.hash_after)


def test_a_good_part_passes_and_a_defective_one_fails_with_the_models_data(cell: Cell) -> None:
    settings = cell.inspection.settings
    assert settings.model is not None
    for image in cell.good:
        outcome = cell.inspection.run(InspectionInput(image), overlay=False)
        assert outcome.passed, outcome.data
        data = outcome.data
        assert set(data) == {"score", "threshold", "method", "model_version", "model_sha256"}
        assert 0 <= data["score"] <= data["threshold"]
        assert data["threshold"] == round(settings.model.threshold, 6)
        assert data["method"] == "variation"
        assert data["model_version"] == 1
        assert data["model_sha256"] == settings.model.digest[:16]
    for kind, image, _ in cell.bad:
        outcome = cell.inspection.run(InspectionInput(image), overlay=False)
        assert not outcome.passed, (kind, outcome.data)
        assert outcome.data["score"] > outcome.data["threshold"]
        summary = RESULT_KINDS["anomaly"].summary(outcome.data)
        assert summary == {"score": outcome.data["score"], "threshold": outcome.data["threshold"]}


def test_the_configurations_threshold_overrides_the_models(cell: Cell) -> None:
    lenient = write(cell.folder, cell.after.replace("method: variation", "threshold: 1000"))
    (inspection,) = load_config(lenient).inspections
    for _, image, _ in cell.bad:
        outcome = inspection.run(InspectionInput(image), overlay=False)
        assert outcome.passed
        assert outcome.data["threshold"] == 1000
    strict = write(cell.folder, cell.after.replace("method: variation", "threshold: 0"))
    (inspection,) = load_config(strict).inspections
    outcome = inspection.run(InspectionInput(cell.good[0]), overlay=False)
    assert not outcome.passed
    assert outcome.data["threshold"] == 0


def test_an_roi_of_another_size_than_the_models_is_a_configuration_error(cell: Cell) -> None:
    text = cell.after.replace(f"roi: [16, 8, {SIZE}, {SIZE}]", f"roi: [16, 8, 200, {SIZE}]")
    with pytest.raises(ConfigError) as caught:
        load_config(write(cell.folder, text))
    message = str(caught.value)
    assert f"trained on {SIZE}x{SIZE} images" in message
    assert f"ROI is 200x{SIZE}" in message
    assert "models/surface.v1.npz" in message
    assert "model" in message
    # Without an ROI the whole image is judged: a request camera's size is not known when the
    # configuration loads, so the image of another size is refused when it runs, naming both.
    whole = "\n".join(line for line in cell.after.splitlines() if "roi:" not in line) + "\n"
    (inspection,) = load_config(write(cell.folder, whole)).inspections
    with pytest.raises(CellvisionError, match=r"300x260 px, the model was trained on 224x224"):
        inspection.run(InspectionInput(cell.good[0]), overlay=False)


@pytest.mark.parametrize(
    ("content", "cause"),
    [(b"", "not a cellvision anomaly model"), (b"\x00garbage" * 30, "not a cellvision")],
    ids=["empty", "garbage"],
)
def test_a_damaged_model_file_is_a_configuration_error_naming_it(
    cell: Cell, content: bytes, cause: str
) -> None:
    (cell.folder / "models" / "broken.npz").write_bytes(content)
    text = cell.after.replace("models/surface.v1.npz", "models/broken.npz")
    with pytest.raises(ConfigError, match=rf"broken\.npz: {cause}"):
        load_config(write(cell.folder, text))


def test_unknown_or_bad_keys_are_configuration_errors(cell: Cell) -> None:
    for old, new, cause in [
        ("method: variation", "method: magic", "method"),
        ("method: variation", "false_reject: 0.7", "false_reject"),
        ("method: variation", "threshold: -1", "threshold"),
        ("method: variation", "tolerance: 3", "tolerance"),
    ]:
        with pytest.raises(ConfigError, match=cause):
            load_config(write(cell.folder, CONFIG.replace(old, new)))


def test_the_overlay_blends_the_heat_map_into_the_roi_and_nowhere_else(cell: Cell) -> None:
    kind, image, mask = cell.bad[1]
    outcome = cell.inspection.run(InspectionInput(image), overlay=True)
    picture = outcome.overlay
    assert picture is not None
    assert picture.shape == image.shape
    data = outcome.data
    reference = overlay_base(image, None)
    u, v, w, h = ROI
    colour = (0, 200, 0) if outcome.passed else (0, 0, 255)  # the ROI red on a fail
    cv2.rectangle(reference, (u, v), (u + w - 1, v + h - 1), colour, 2)
    label = f"anomaly {data['score']:.3g} / {data['threshold']:.3g}"
    draw_verdict(reference, outcome.passed, label)
    changed = np.any(picture != reference, axis=2)
    u, v, w, h = ROI
    inside = np.zeros(changed.shape, bool)
    inside[v : v + h, u : u + w] = True
    assert not changed[~inside].any(), "the heat map reached outside the ROI"
    assert changed[inside].mean() > 0.8, "the heat map is not blended into the ROI"
    # The defect is drawn hot (red), the good surface cold (blue).
    peak = np.unravel_index(int(np.argmax(np.where(mask, 1, 0))), mask.shape)
    ys, xs = np.nonzero(mask)
    hot = picture[ys, xs].astype(int)
    assert (hot[:, 2] - hot[:, 0]).max() > 40, (kind, peak)
    cold = picture[v + 100 : v + 110, u + 180 : u + 190].reshape(-1, 3).astype(int)
    assert (cold[:, 0] > cold[:, 2]).mean() > 0.9


def test_the_inspection_runs_through_patches_too(cell: Cell) -> None:
    """The learned method end to end on a few images (the minimum): a hole fails."""
    path = write(cell.folder, CONFIG.replace("method: variation", "method: patches"), "p.yaml")
    config = load_config(path)
    rng = np.random.default_rng(12)
    images = [scene(good_part(rng)) for _ in range(8)]
    text = path.read_text(encoding="utf-8")
    trained = train_inspection(config, text, "surface", images)
    assert trained.model.method == "patches"
    path.write_text(trained.text, encoding="utf-8")
    (inspection,) = load_config(path).inspections
    hole = next(image for kind, image, _ in cell.bad if kind == "hole")
    outcome = inspection.run(InspectionInput(hole), overlay=False)
    assert not outcome.passed
    assert outcome.data["method"] == "patches"


# --- the job step ---------------------------------------------------------------------------

JOB = f"""\
cameras:
  qc: {{source: request}}
inspections:
  - name: plate
    type: job
    camera: qc
    steps:
      - name: big_hole
        type: locate
        method: circle
        circle: {{min_radius_px: 10, max_radius_px: 15, polarity: dark}}
        max_count: 1
      - name: near
        type: fixture
        origin: big_hole
      - name: small_hole
        type: locate
        fixture: near
        roi: [60, -50, 80, 100]
        method: circle
        circle: {{min_radius_px: 6, max_radius_px: 11, polarity: dark}}
        max_count: 1
      - name: part
        type: fixture
        origin: big_hole
        x_towards: small_hole
      - name: surface
        type: anomaly
        fixture: part
        roi: [{PLATE_WINDOW[0]}, {PLATE_WINDOW[1]}, {PLATE_WINDOW[2]}, {PLATE_WINDOW[3]}]
        method: variation
    verdict: all(big_hole, part, surface)
"""


def pose(rng: np.random.Generator) -> tuple[float, float, float]:
    """A plate where a belt brings it: ±25 px, ±15°."""
    return (
        130.0 + rng.uniform(-25, 25),
        120.0 + rng.uniform(-25, 25),
        math.radians(rng.uniform(-15, 15)),
    )


@pytest.fixture(scope="module")
def job(tmp_path_factory: pytest.TempPathFactory) -> tuple[JobInspection, Any]:
    folder = tmp_path_factory.mktemp("anomaly_job")
    path = folder / "cell.yaml"
    path.write_text(JOB, encoding="utf-8")
    config = load_config(path)
    rng = np.random.default_rng(21)
    images = [placed_plate(rng, *pose(rng))[0] for _ in range(24)]
    (untrained,) = config.inspections
    patches, skipped = training_patches(untrained, images, step="surface")
    assert skipped == []
    assert {patch.shape for patch in patches} == {(PLATE_WINDOW[3], PLATE_WINDOW[2])}
    trained = train_inspection(config, JOB, "plate", images)  # the one anomaly step
    assert trained.relative == "models/plate.surface.v1.npz"
    assert trained.model.image_size == PLATE_WINDOW[2:]
    path.write_text(trained.text, encoding="utf-8")
    (inspection,) = load_config(path).inspections
    assert isinstance(inspection, JobInspection)
    return inspection, trained


def test_an_untrained_step_names_the_job_and_the_step_to_train(tmp_path: Path) -> None:
    (inspection,) = load_config(write(tmp_path, JOB)).inspections
    image, _ = placed_plate(np.random.default_rng(1), 130.0, 120.0, 0.0)
    with pytest.raises(InspectionFailed) as caught:
        inspection.run(InspectionInput(image), overlay=False)
    message = caught.value.message
    assert "step 'surface' of 'plate' has no trained model" in message
    assert "vision-server train plate --step surface --config CONFIG --images" in message


def test_the_job_step_judges_the_part_located_and_aligned(
    job: tuple[JobInspection, Any],
) -> None:
    inspection, trained = job
    rng = np.random.default_rng(77)
    for _ in range(4):
        image, _ = placed_plate(rng, *pose(rng))
        outcome = inspection.run(InspectionInput(image), overlay=False)
        assert outcome.passed, outcome.data["steps"]
        step = outcome.data["steps"]["surface"]
        assert step["passed"] is True
        assert step["score"] <= step["threshold"]
        assert step["model_version"] == 1
        assert step["model_sha256"] == hashlib.sha256(trained.path.read_bytes()).hexdigest()[:16]
    for kind in DEFECTS:
        image, _ = placed_plate(rng, *pose(rng), defect=kind)
        outcome = inspection.run(InspectionInput(image), overlay=False)
        assert not outcome.passed, (kind, outcome.data["steps"]["surface"])
        assert outcome.data["failed"] == ["surface"]
        step = outcome.data["steps"]["surface"]
        assert step["score"] > step["threshold"]


def test_the_job_step_with_a_fixed_roi_misjudges_a_moved_part(
    job: tuple[JobInspection, Any], tmp_path: Path
) -> None:
    """What the fixture is for: the same model on a fixed ROI fails a good part that moved."""
    inspection, trained = job
    rng = np.random.default_rng(78)
    moved, _ = placed_plate(rng, 160.0, 140.0, math.radians(20))
    assert inspection.run(InspectionInput(moved), overlay=False).passed
    fixed = (
        JOB.replace("        fixture: part\n        roi: [20, -40", "        roi: [120, 80")
        .replace("method: variation", f'model: "{trained.path}"')
        .replace("verdict: all(big_hole, part, surface)", "verdict: surface")
    )
    (stuck,) = load_config(write(tmp_path, fixed)).inspections
    outcome = stuck.run(InspectionInput(moved), overlay=False)
    assert not outcome.passed


def test_the_job_overlay_has_the_heat_map_in_the_parts_frame(
    job: tuple[JobInspection, Any],
) -> None:
    inspection, _ = job
    rng = np.random.default_rng(79)
    image, mask = placed_plate(rng, 140.0, 110.0, math.radians(-15), defect="hole")
    assert mask is not None
    outcome = inspection.run(InspectionInput(image), overlay=True)
    assert not outcome.passed
    picture = outcome.overlay
    assert picture is not None
    ys, xs = np.nonzero(mask)
    hot = picture[ys, xs].astype(int)
    assert (hot[:, 2] - hot[:, 0]).max() > 40
    # A corner of the camera image far from the plate keeps its grey.
    corner = picture[-20:, -20:].astype(int)
    assert (np.abs(corner[..., 0] - corner[..., 2]) < 3).all()


def test_an_unfixtured_job_step_draws_its_heat_map_over_its_roi(cell: Cell) -> None:
    """A job step without a fixture judges its fixed ROI; the heat map lands there."""
    model = cell.folder / "models" / "surface.v1.npz"
    text = f"""\
cameras:
  cam: {{source: request}}
inspections:
  - name: line
    type: job
    camera: cam
    steps:
      - name: face
        type: anomaly
        roi: [{ROI[0]}, {ROI[1]}, {ROI[2]}, {ROI[3]}]
        model: "{model}"
"""
    (job,) = load_config(write(cell.folder, text, "job.yaml")).inspections
    good = job.run(InspectionInput(cell.good[0]), overlay=False)
    assert good.passed, good.data
    direct = cell.inspection.run(InspectionInput(cell.good[0]), overlay=False)
    assert good.data["steps"]["face"]["score"] == direct.data["score"]
    kind, image, mask = cell.bad[1]
    outcome = job.run(InspectionInput(image), overlay=True)
    assert not outcome.passed
    assert outcome.data["failed"] == ["face"]
    picture = outcome.overlay
    assert picture is not None
    ys, xs = np.nonzero(mask)
    hot = picture[ys, xs].astype(int)
    assert (hot[:, 2] - hot[:, 0]).max() > 40, kind
    # Below and right of the ROI the belt keeps its grey.
    u, v, w, h = ROI
    outside = picture[v + h + 2 :, u + w + 2 :].astype(int)
    assert outside.size
    assert (np.abs(outside[..., 0] - outside[..., 2]) < 3).all()


def test_a_job_steps_roi_of_another_size_or_its_threshold(
    job: tuple[JobInspection, Any], tmp_path: Path
) -> None:
    _, trained = job
    with_model = JOB.replace("method: variation", f'model: "{trained.path}"')
    w, h = PLATE_WINDOW[2:]
    resized = with_model.replace(f"{w}, {h}]", f"{w}, {h + 8}]")
    with pytest.raises(ConfigError) as caught:
        load_config(write(tmp_path, resized))
    message = str(caught.value)
    assert f"trained on {w}x{h} images; this step's ROI is {w}x{h + 8}" in message
    assert "steps[4] (name='surface') -> model" in message
    lenient = with_model.replace(
        f'model: "{trained.path}"', f'model: "{trained.path}"\n        threshold: 100000.0'
    )
    (inspection,) = load_config(write(tmp_path, lenient)).inspections
    rng = np.random.default_rng(80)
    image, _ = placed_plate(rng, 130.0, 120.0, 0.1, defect="hole")
    outcome = inspection.run(InspectionInput(image), overlay=False)
    assert outcome.passed, outcome.data["steps"]["surface"]
    assert outcome.data["steps"]["surface"]["threshold"] == 100000.0
