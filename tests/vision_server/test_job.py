"""``type: job``: steps chained in one inspection. A fixture makes the later ROIs follow a part
that moved and turned (the same presence step with a fixed ROI fails there); a code is read in
the part's frame through a real server on loopback, with every step's values in one RESULT and
one overlay; the validator names every broken link of the chain with file, line and key path."""

from __future__ import annotations

import math
import re
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pytest
from loopback import client_for, run, server_in_thread

from protocol import schema
from robot_client.client import overlay_image
from vision_server import InspectionInput
from vision_server.config import ConfigError, Node, load_config
from vision_server.inspections import RESULT_KINDS, JobInspection
from vision_server.inspections.job import STEP_TYPES
from vision_server.service import CellRuntime

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
"""
LOCATE = """\
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


def job(tmp_path: Path, steps: str, verdict: str | None = None) -> JobInspection:
    text = HEAD + LOCATE + steps + (f"    verdict: {verdict}\n" if verdict else "")
    path = tmp_path / "cell.yaml"
    path.write_text(text, encoding="utf-8")
    (inspection,) = load_config(path).inspections
    assert isinstance(inspection, JobInspection)
    return inspection


def plate(name: str) -> np.ndarray:
    image = cv2.imread(str(PLATES / name), cv2.IMREAD_GRAYSCALE)
    assert image is not None, name
    return image


MAGNET_IN_PART = """\
      - name: magnet
        type: presence
        fixture: part
        roi: [44, 12, 12, 12]
        measure: dark_fraction
        threshold: 110
        min: 0.6
"""
# The same ROI where the magnet is on the taught image (big hole at (110, 120), angle 0).
MAGNET_FIXED = """\
      - name: magnet
        type: presence
        roi: [154, 132, 12, 12]
        measure: dark_fraction
        threshold: 110
        min: 0.6
"""


@pytest.mark.parametrize("name", ["moved_a.png", "moved_b.png", "moved_c.png"])
def test_the_fixture_makes_the_roi_follow_a_moved_and_turned_part(
    tmp_path: Path, name: str
) -> None:
    fixtured = job(tmp_path, MAGNET_IN_PART)
    fixed = job(tmp_path, MAGNET_FIXED)
    # Taught where the fixed ROI was drawn, both see the magnet.
    for inspection in (fixtured, fixed):
        taught = inspection.run(InspectionInput(plate("taught.png")), overlay=False)
        assert taught.passed, taught.data["steps"]["magnet"]
    moved = fixtured.run(InspectionInput(plate(name)), overlay=False)
    assert moved.passed, moved.data["steps"]
    assert moved.data["steps"]["magnet"]["value"] > 0.9
    stuck = fixed.run(InspectionInput(plate(name)), overlay=False)
    assert not stuck.passed
    assert stuck.data["failed"] == ["magnet"]
    assert stuck.data["steps"]["magnet"]["value"] < 0.3


def test_a_missing_magnet_fails_its_step_and_a_missing_part_skips_the_chain(
    tmp_path: Path,
) -> None:
    inspection = job(tmp_path, MAGNET_IN_PART, "all(big_hole, part) and magnet.value >= 0.6")
    empty = inspection.run(InspectionInput(plate("moved_empty.png")), overlay=False)
    assert not empty.passed
    assert empty.data["failed"] == ["magnet"]
    nothing = inspection.run(InspectionInput(plate("no_plate.png")), overlay=True)
    assert not nothing.passed
    steps = nothing.data["steps"]
    assert steps["big_hole"]["count"] == 0
    assert steps["near"]["reason"] == "step 'big_hole' found nothing"
    assert steps["magnet"] == {
        "type": "presence",
        "passed": False,
        "value": None,
        "reason": "fixture 'part' was not made",
    }
    assert nothing.data["count"] == 0
    assert nothing.overlay is not None
    schema.validate_data("job", nothing.data)
    summary = RESULT_KINDS["job"].summary(nothing.data)
    assert summary["failed"] == 5.0
    assert math.isnan(summary["u"])


def test_an_roi_that_the_fixture_moves_out_of_the_image_fails_with_its_reason(
    tmp_path: Path,
) -> None:
    far = MAGNET_IN_PART.replace("roi: [44, 12, 12, 12]", "roi: [300, 0, 12, 12]")
    outcome = job(tmp_path, far).run(InspectionInput(plate("taught.png")), overlay=False)
    assert not outcome.passed
    assert outcome.data["steps"]["magnet"]["reason"] == (
        "ROI [300, 0, 12, 12] in fixture 'part''s frame leaves the image"
    )


# ----------------------------------------------------------------------- a code, over the wire

LABEL = "P-4711/07"
PART_FROM_CANVAS = (30.0, 60.0)
"""Where the part frame's origin (the big hole) lies on the drawn part canvas, in pixels."""


def turned_part(u0: float, v0: float, angle: float) -> tuple[np.ndarray, np.ndarray]:
    """A bright part with the two holes of the plate and a DataMatrix label, placed with its
    frame at (u0, v0) turned by ``angle`` (rad) in a 400x300 image; and the label's four
    corners in image pixels (the truth)."""
    import zxingcpp

    canvas = np.full((120, 200), 200, np.uint8)
    ox, oy = PART_FROM_CANVAS
    cv2.circle(canvas, (int(ox), int(oy)), 12, 40, -1, cv2.LINE_AA)
    cv2.circle(canvas, (int(ox) + 100, int(oy)), 7, 40, -1, cv2.LINE_AA)
    symbol = zxingcpp.create_barcode(LABEL, zxingcpp.BarcodeFormat.DataMatrix)
    code = np.asarray(zxingcpp.write_barcode_to_image(symbol, scale=3, add_quiet_zones=False))
    size = code.shape[0]
    x0, y0 = int(ox) + 45, int(oy) - size // 2
    canvas[y0 : y0 + size, x0 : x0 + size] = code
    c, s = math.cos(angle), math.sin(angle)
    # image = R (canvas - origin) + (u0, v0)
    matrix = np.array([[c, -s, u0 - c * ox + s * oy], [s, c, v0 - s * ox - c * oy]])
    image = cv2.warpAffine(canvas, matrix, (400, 300), flags=cv2.INTER_LINEAR, borderValue=40)
    corners = (
        np.array([[x0, y0], [x0 + size, y0], [x0 + size, y0 + size], [x0, y0 + size]], float) - 0.5
    )
    return image, corners @ matrix[:, :2].T + matrix[:, 2]


CODE_CONFIG = (
    HEAD.replace("  qc: {source: request}", "  qc: {source: request}").replace(
        "cameras:", "server: {port: 0}\nresults: {enabled: false}\ncameras:"
    )
    + LOCATE.replace("[60, -50, 80, 100]", "[60, -60, 80, 120]")
    + f"""\
      - name: label
        type: code
        fixture: part
        roi: [35, -30, 60, 60]
        symbologies: [datamatrix]
        expect: {LABEL}
    verdict: all(part, label) and label.text == "{LABEL}" and small_hole.count == 1
"""
)


@pytest.fixture
def runtime(tmp_path: Path) -> Iterator[CellRuntime]:
    path = tmp_path / "cell.yaml"
    path.write_text(CODE_CONFIG, encoding="utf-8")
    cell = CellRuntime(path)
    try:
        yield cell
    finally:
        cell.close()


def test_a_code_is_read_in_the_turned_part_frame_in_one_result_with_every_step(
    runtime: CellRuntime,
) -> None:
    image, truth = turned_part(215.3, 140.6, math.radians(25.0))

    async def body() -> tuple[bool, dict[str, Any], Any]:
        with server_in_thread(runtime.catalog) as server:
            async with client_for(server) as client:
                result = await client.inspect("plate", image, overlay=True)
                return result.passed, dict(result.data), overlay_image(result)

    passed, data, picture = run(body())
    assert passed, data
    schema.validate_data("job", data)
    assert set(data["steps"]) == {"big_hole", "near", "small_hole", "part", "label"}
    part = data["steps"]["part"]
    assert part["u"] == pytest.approx(215.3, abs=0.3)
    assert part["v"] == pytest.approx(140.6, abs=0.3)
    assert part["angle"] == pytest.approx(math.radians(25.0), abs=0.01)
    # what a PLC (Modbus) or a robot controller (line protocol) reads of it
    summary = RESULT_KINDS["job"].summary(data)
    assert list(summary)[:4] == ["failed", "u", "v", "angle"]
    assert [summary[k] for k in ("failed", "u", "v", "angle")] == [
        0.0,
        part["u"],
        part["v"],
        part["angle"],
    ]
    # and each step's numbers as STEP.VALUE (a code's text is no number: not among them)
    assert summary["label.found"] == 1.0
    assert summary["part.angle"] == part["angle"]
    assert "label.text" not in summary
    label = data["steps"]["label"]
    assert label["text"] == LABEL
    assert label["symbology"] == "datamatrix"
    # zxing-cpp's corners are whole-pixel estimates of the outer modules: ~1.5 px
    errors = np.hypot(*(np.asarray(label["corners"]) - truth).T)
    assert errors.max() < 2.5, (label["corners"], truth.tolist())
    assert data["verdict"].startswith("all(part, label)")
    # The overlay shows the label's ROI where the fixture put it: a green edge along the
    # turned ROI's top side, away from the image's axes.
    assert picture is not None
    assert picture.shape[:2] == image.shape
    m = np.array(
        [[math.cos(math.radians(25)), -math.sin(math.radians(25))],
         [math.sin(math.radians(25)), math.cos(math.radians(25))]]
    )  # fmt: skip
    u, v = m @ np.array([65.0, -30.5]) + np.array([part["u"], part["v"]])
    patch = picture[int(v) - 2 : int(v) + 3, int(u) - 2 : int(u) + 3].reshape(-1, 3)
    green = (patch[:, 1] > 150) & (patch[:, 2] < 100) & (patch[:, 0] < 100)
    assert green.any(), patch


def test_a_code_below_its_minimum_grade_fails_its_step_with_the_reason(tmp_path: Path) -> None:
    image, _ = turned_part(160.0, 150.0, math.radians(-20.0))
    label = """\
      - name: label
        type: code
        fixture: part
        roi: [35, -30, 60, 60]
        min_grade: {module_px: 50}
"""
    outcome = job(tmp_path, label).run(InspectionInput(image), overlay=False)
    assert not outcome.passed
    step = outcome.data["steps"]["label"]
    assert step["text"] == LABEL
    assert step["passed"] is False
    assert step["reason"].startswith("grade below the minimum: module_px 3")


def test_a_fixture_can_take_its_angle_from_a_blob(tmp_path: Path) -> None:
    """``angle_from``: the frame turns with the plate's own orientation (its blob's second
    moments), here without the second hole."""
    image, _ = turned_part(190.0, 160.0, math.radians(-30.0))
    steps = """\
      - name: plate
        type: locate
        method: blob
        blob: {polarity: bright, threshold: 120, min_area_px: 5000}
        max_count: 1
      - name: tilted
        type: fixture
        origin: big_hole
        angle_from: plate
      - name: label
        type: code
        fixture: tilted
        roi: [35, -30, 60, 60]
        expect: P-4711/07
"""
    inspection = job(tmp_path, steps, "all(tilted, label)")
    outcome = inspection.run(InspectionInput(image), overlay=False)
    assert outcome.passed, outcome.data["steps"]
    tilted = outcome.data["steps"]["tilted"]
    assert tilted["angle"] == pytest.approx(math.radians(-30.0), abs=0.03)
    assert tilted["u"] == pytest.approx(190.0, abs=0.3)


# ----------------------------------------------------------------------- the validator


def error_of(tmp_path: Path, steps: str, verdict: str | None = None) -> ConfigError:
    with pytest.raises(ConfigError) as info:
        job(tmp_path, steps, verdict)
    return info.value


@pytest.mark.parametrize(
    ("steps", "verdict", "marker", "path", "reason"),
    [
        (
            MAGNET_IN_PART.replace("fixture: part", "fixture: parts"),
            None,
            "fixture: parts",
            "inspections[0] (name='plate') -> steps[4] (name='magnet') -> fixture",
            "no step named 'parts' (the steps are: big_hole, near, small_hole, part, magnet)",
        ),
        (
            MAGNET_IN_PART.replace("fixture: part", "fixture: magnet"),
            None,
            "fixture: magnet",
            "steps[4] (name='magnet') -> fixture",
            "step 'magnet' runs later than this one: a step can use only the steps before it "
            "(here: big_hole, near, small_hole, part)",
        ),
        (
            MAGNET_IN_PART.replace("fixture: part", "fixture: small_hole"),
            None,
            "fixture: small_hole",
            "steps[4] (name='magnet') -> fixture",
            "step 'small_hole' is a locate step; fixture needs a fixture step",
        ),
        (
            MAGNET_IN_PART + "      - {name: tilt, type: fixture, origin: big_hole, "
            "angle_from: big_hole}\n",
            None,
            "angle_from: big_hole",
            "steps[5] (name='tilt') -> angle_from",
            "step 'big_hole' gives no angle (a circle has none)",
        ),
        (
            MAGNET_IN_PART
            + "      - {name: again, type: fixture, fixture: part, origin: big_hole}\n",
            None,
            "name: again",
            "steps[5] (name='again') -> fixture",
            "a fixture step is not in another's frame",
        ),
        (
            MAGNET_IN_PART.replace("        roi: [44, 12, 12, 12]\n", ""),
            None,
            "fixture: part",
            "steps[4] (name='magnet') -> fixture",
            "a step in a fixture's frame needs an roi [x, y, width, height] in that frame",
        ),
        (
            MAGNET_IN_PART.replace("name: magnet", "name: part"),
            None,
            "name: part",
            "steps[4] (name='part') -> name",
            "a second step named 'part'",
        ),
        (
            MAGNET_IN_PART.replace("type: presence", "type: gauge"),
            None,
            "type: gauge",
            "steps[4] (name='magnet') -> type",
            "expected one of locate, fixture, presence, code, caliper, anomaly, got 'gauge'",
        ),
        (
            MAGNET_IN_PART.replace(
                "measure: dark_fraction", "measure: dark_fraction\n        x: 1"
            ),
            None,
            "x: 1",
            "steps[4] (name='magnet') -> x",
            "unknown key",
        ),
        (
            MAGNET_IN_PART,
            "magnet.count >= 1",
            "verdict:",
            "inspections[0] (name='plate') -> verdict",
            "step 'magnet' has no value 'count' (column 1); it gives: passed, value",
        ),
        (
            MAGNET_IN_PART,
            "magnet and holes",
            "verdict:",
            "inspections[0] (name='plate') -> verdict",
            "unknown step 'holes' at column 12",
        ),
        (
            MAGNET_FIXED.replace("roi: [154, 132, 12, 12]", "roi: [-4, 132, 12, 12]"),
            None,
            "roi: [-4",
            "steps[4] (name='magnet') -> roi",
            "an ROI in the image needs u, v >= 0",
        ),
    ],
)
def test_the_validator_names_each_broken_link_with_file_line_and_key(
    tmp_path: Path, steps: str, verdict: str | None, marker: str, path: str, reason: str
) -> None:
    """``marker``: text on the line the error must name (its last line holding it)."""
    error = error_of(tmp_path, steps, verdict)
    text = (tmp_path / "cell.yaml").read_text(encoding="utf-8").splitlines()
    line = max(number for number, row in enumerate(text, start=1) if marker in row)
    assert error.source == "cell.yaml"
    assert error.line == line, str(error)
    assert path in error.path, str(error)
    assert reason in error.reason, str(error)


def test_a_template_larger_than_its_steps_roi_is_refused_at_load(tmp_path: Path) -> None:
    """The step's ROI (in the part frame) bounds the template as an inspection's ROI does."""
    texture = np.arange(400, dtype=np.uint8).reshape(20, 20)
    cv2.imwrite(str(tmp_path / "magnet.png"), texture)
    steps = MAGNET_IN_PART.replace(
        "measure: dark_fraction\n        threshold: 110\n        min: 0.6",
        "measure: template_score\n        template: magnet.png\n        min: 0.6",
    )
    error = error_of(tmp_path, steps)
    assert error.path.endswith("steps[4] (name='magnet') -> template"), str(error)
    assert "is larger than the 12x12 ROI it is searched in" in error.reason, str(error)


# ----------------------------------------------------------------------- the docs

DOC = ROOT / "docs" / "configuration.md"
COMMON = {"name", "type", "camera", "roi", "frames", "description", "number", "output"}
"""The keys every inspection has (docs/configuration.md, ``## inspections``)."""
REFUSED = {"show_rejected"}
"""Keys the docs name only to say a job's step refuses them."""


def _job_section() -> str:
    text = DOC.read_text(encoding="utf-8")
    return text.split("### type: job\n", 1)[1].split("\n#### ", 1)[0]


def test_the_docs_list_exactly_the_keys_a_job_and_its_steps_read(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The keys the validator looks at (given or not), by job, step and step type, against the
    tables of docs/configuration.md's ``type: job``."""
    read: dict[str, set[str]] = {}
    original_take, original_sub, original_items = Node.take, Node.sub, Node.items
    original_optional = Node.sub_optional

    def section(node: Node) -> str | None:
        path = node.path
        if path[:1] != ("inspections",):
            return None
        if len(path) == 2:
            return "job"
        if len(path) == 4 and path[2] == "steps":
            return f"step {node.data.get('type')}"
        return None

    def take(self: Node, key: str, convert: Any, *default: Any) -> Any:
        if (where := section(self)) is not None:
            read.setdefault(where, set()).add(key)
        return original_take(self, key, convert, *default)

    def sub(self: Node, key: str, *, required: bool = False) -> Node:
        if (where := section(self)) is not None:
            read.setdefault(where, set()).add(key)
        return original_sub(self, key, required=required)

    def items(self: Node, key: str) -> list[Node]:
        if (where := section(self)) is not None:
            read.setdefault(where, set()).add(key)
        return original_items(self, key)

    monkeypatch.setattr(Node, "take", take)
    monkeypatch.setattr(Node, "sub", sub)

    def sub_optional(self: Node, key: str) -> Node | None:
        if (where := section(self)) is not None:
            read.setdefault(where, set()).add(key)
        return original_optional(self, key)

    monkeypatch.setattr(Node, "items", items)
    monkeypatch.setattr(Node, "sub_optional", sub_optional)
    caliper = (
        "      - {name: gauge, type: caliper, fixture: part, measurements: [{name: w,"
        " kind: width, band: {center: [75, 0], length: 100}}]}\n"
    )
    code = "      - {name: label, type: code, symbologies: [qr]}\n"
    anomaly = "      - {name: surface, type: anomaly, fixture: part, roi: [0, 0, 32, 32]}\n"
    job(tmp_path, MAGNET_IN_PART + code + caliper + anomaly)
    monkeypatch.undo()

    rows: dict[str, list[str]] = {}
    for line in _job_section().splitlines():
        cells = [c.strip() for c in line.split("|")[1:-1]]
        if len(cells) >= 3 and cells[0].startswith("`"):
            rows[cells[0].strip("`")] = cells
    step_common = {"name", "type", "fixture", "roi"}
    documented = set(rows)
    assert documented == (read["job"] - COMMON) | step_common | set(STEP_TYPES), documented
    for step_type in STEP_TYPES:
        keys = set(re.findall(r"`([a-z_]+)`", rows[step_type][1])) - REFUSED
        got = read[f"step {step_type}"] - step_common
        assert got == keys, f"{step_type}: validator reads {sorted(got)}, docs list {sorted(keys)}"


def test_a_job_stops_between_steps_once_its_deadline_passed(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Work nobody waits for does not hold a worker: a job whose request's deadline passed
    (a try's 10 s; a draft job of 32 slow searches held the try lane for 264 s) stops before its
    next step with DEADLINE_EXCEEDED naming how far it came; without a deadline it runs whole."""
    import types

    from protocol import DeadlineExceeded
    from vision_server.inspections.job import inspection as job_module

    fixtured = job(tmp_path, MAGNET_IN_PART)
    image = plate("taught.png")
    assert fixtured.run(InspectionInput(image), overlay=False).passed
    # The job's clock reads a second later each time it looks (once before each step).
    ticks = iter(range(1000, 1100))
    monkeypatch.setattr(job_module, "time", types.SimpleNamespace(monotonic=lambda: next(ticks)))
    with pytest.raises(DeadlineExceeded, match=r"before step 'small_hole' \(2 of 5 steps ran\)"):
        fixtured.run(InspectionInput(image, deadline=1001.5), overlay=False)
