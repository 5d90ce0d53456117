"""What can be tested and read out of a job: a golden case's expected entry names the failed
steps, step values and the part frame's angle; a PLC (Modbus) and a robot (line protocol) read
a step's measurement as ``STEP.VALUE``; no reader sees a negative zero."""

from __future__ import annotations

import asyncio
import contextlib
import io
import json
import math
import re
import shutil
import struct
from pathlib import Path

import cv2
import numpy as np
import pytest
from controllers import read_line
from loopback import run
from plc import Plc

from protocol.result_view import format_number
from vision_server import InspectionInput
from vision_server.analysis import Rejection, locate_circles
from vision_server.app import App
from vision_server.commands import main as cli_main
from vision_server.commands.golden import run_case
from vision_server.config import ConfigError, ServerSettings, load_config
from vision_server.frontends.modbus_map import Status
from vision_server.inspections import JobInspection
from vision_server.service import CellRuntime

ROOT = Path(__file__).resolve().parents[2]
PLATE_CASE = ROOT / "test_inspections" / "fixtured_plate"
PLATES = PLATE_CASE / "images"


def plate_job() -> str:
    """The fixtured_plate case's job entry (locate, fixture, presence, caliper), as YAML text
    indented for ``inspections:``."""
    text = (PLATE_CASE / "inspection.yaml").read_text(encoding="utf-8")
    entry = text[text.index("inspection:\n") + len("inspection:\n") :]
    lines = ["  " + line if line.strip() else line for line in entry.splitlines()]
    return "  - " + "\n".join(lines).lstrip()


# ----------------------------------------------------------------------------- golden


def golden_case(tmp_path: Path, entry: str) -> Path:
    """A case over the plate images (a pool) whose expected.yaml holds ``entry`` for
    moved_narrow.png (a plate 74 px wide: the caliper step fails)."""
    case = tmp_path / "case"
    case.mkdir(parents=True)
    inspection = (PLATE_CASE / "inspection.yaml").read_text(encoding="utf-8")
    (case / "inspection.yaml").write_text(inspection + f"images: {PLATES}\n", encoding="utf-8")
    (case / "expected.yaml").write_text(
        "images:\n  moved_narrow.png:\n    verdict: fail\n" + entry, encoding="utf-8"
    )
    return case


def test_a_job_golden_entry_checks_failed_steps_step_values_and_angle(tmp_path: Path) -> None:
    right = (
        "    failed: [gauge]\n"
        "    angle: 0.3803\n"
        "    steps: {gauge: {plate_width: 74.27, failed: 1, passed: false}, magnet: {value: 1.0}}\n"
    )
    report = run_case(golden_case(tmp_path / "right", right))
    assert report.error is None, report.error
    assert [(i.status, i.problems) for i in report.images] == [("pass", [])]

    wrong = (
        "    failed: [magnet]\n"
        "    angle: -0.2\n"
        "    tolerance_value: 0.05\n"
        "    steps: {gauge: {plate_width: 79.0}}\n"
    )
    report = run_case(golden_case(tmp_path / "wrong", wrong))
    assert report.error is None, report.error
    (image,) = report.images
    assert image.status == "regression"
    assert image.got == "fail, 2 found, failed: gauge"  # the table's "got" column
    assert re.fullmatch(r"angle 0\.380\d rad, expected -0\.2 ± 0\.01 rad", image.problems[0])
    assert image.problems[1:] == [
        "failed steps: gauge; expected: magnet",
        "gauge.plate_width 74.27, expected 79.0 ± 0.05",
    ]


def test_update_measures_the_step_values_an_entry_checks_again(tmp_path: Path) -> None:
    case = golden_case(tmp_path, "    steps: {gauge: {plate_width: 1.0}}\n    note: narrow\n")
    report = run_case(case, update=True)
    assert report.error is None, report.error
    text = (case / "expected.yaml").read_text(encoding="utf-8")
    entry = text[text.index("moved_narrow.png:") :]
    assert re.search(r"\n    steps: \{gauge: \{plate_width: 74\.2\d+\}\}\n", entry), entry
    assert "note: narrow" in entry
    assert run_case(case).images[0].status == "pass"  # and it reads back


@pytest.mark.parametrize(
    ("entry", "message"),
    [
        (
            "    value: 74.3\n",
            "'value' is not a result of a job inspection (a job's expected entry checks: "
            "count, features, angle, failed, steps)",
        ),
        (
            "    tolerance_m: 0.1\n",
            "unknown key (allowed here: angle, count, error, failed, features, note, steps, "
            "tolerance_px, tolerance_rad, tolerance_value, verdict)",
        ),
        ("    failed: [gage]\n", "no step named 'gage' (the steps are: big_hole, near,"),
        (
            "    steps: {gauge: {width: 74.3}}\n",
            "step 'gauge' has no value 'width' (it has: passed, failed, plate_width)",
        ),
        ("    steps: {gauge: {plate_width: wide}}\n", "gauge.plate_width is a number value"),
    ],
)
def test_a_job_golden_entry_takes_exactly_what_a_job_gives(
    tmp_path: Path, entry: str, message: str
) -> None:
    report = run_case(golden_case(tmp_path, entry))
    assert report.error is not None
    assert message in report.error
    assert "expected.yaml" in report.error


# ----------------------------------------------------------------------------- read-out


def readout_cell(tmp_path: Path, fields: str) -> Path:
    folder = tmp_path / "imgs"
    folder.mkdir()
    shutil.copy(PLATES / "taught.png", folder / "taught.png")
    path = tmp_path / "cell.yaml"
    path.write_text(
        "server: {port: 0}\n"
        "results: {enabled: false}\n"
        "cameras:\n"
        "  qc: {source: folder, path: imgs}\n"
        "inspections:\n"
        f"{plate_job()}\n"
        f"    output: {{fields: {fields}, decimals: 3}}\n"
        "line: {enabled: true, port: 0}\n"
        "modbus: {enabled: true, port: 0, word_order: high_first}\n",
        encoding="utf-8",
    )
    return path


def test_a_plc_and_a_robot_read_a_jobs_step_values_without_a_negative_zero(
    tmp_path: Path,
) -> None:
    # taught.png: the plate at its taught place, 80.4 px wide; the part frame's angle is
    # -0.00017 rad, which rounds to a zero that must not be negative
    path = readout_cell(tmp_path, "[failed, gauge.plate_width, magnet.value, part.angle, angle]")

    async def body() -> None:
        runtime = CellRuntime(path)
        app = App(
            runtime.catalog,
            ServerSettings(port=0),
            line=runtime.config.line,
            modbus=runtime.config.modbus,
        )
        try:
            async with app:
                assert app.line is not None
                reader, writer = await asyncio.open_connection("127.0.0.1", app.line.port)
                writer.write(b"T plate_magnet\r\n")
                answer = await read_line(reader)
                assert answer == "OK 1 0.000 80.398 1.000 0.000 0.000"
                writer.close()
                assert app.modbus is not None
                plc = await Plc(app.modbus.port, "high_first").connect()
                result = await plc.run(1)
                assert result.status == Status.DONE | Status.PASS
                assert result.values[0] == 0.0
                assert result.values[1] == pytest.approx(80.398, abs=1e-4)
                assert result.values[2] == 1.0
                signs = [math.copysign(1.0, v) for v in result.values[3:]]
                assert result.values[3:] == [0.0, 0.0]
                assert signs == [1.0, 1.0], "a negative zero reached the registers"
                plc.close()
        finally:
            runtime.close()

    run(body())


def test_the_register_map_gives_a_step_values_unit_by_its_name(tmp_path: Path) -> None:
    path = readout_cell(tmp_path, "[failed, part.angle, magnet.passed, big_hole.radius]")
    out = io.StringIO()
    with contextlib.redirect_stdout(out):
        assert cli_main(["modbus-map", str(path), "--json"]) == 0
    (inspection,) = json.loads(out.getvalue())["inspections"]
    units = {value["field"]: value["units"] for value in inspection["values"]}
    assert units == {
        "failed": "steps",
        "part.angle": "rad",
        "magnet.passed": "1/0",
        "big_hole.radius": "px",
    }


def test_an_output_names_only_step_values_a_register_can_hold(tmp_path: Path) -> None:
    (tmp_path / "a").mkdir()
    path = readout_cell(tmp_path / "a", "[gauge.width]")
    with pytest.raises(ConfigError) as unknown:
        load_config(path)
    message = str(unknown.value)
    assert "job results have no summary value 'gauge.width'" in message
    assert "gauge.plate_width" in message
    assert "magnet.value" in message
    assert "-> output -> fields[0]" in message

    # a code's payload is text: said so at load, not sent as a number
    (tmp_path / "b").mkdir()
    text = readout_cell(tmp_path / "b", "[label.text]").read_text(encoding="utf-8")
    label = (
        "\n      - name: label\n        type: code\n        symbologies: [datamatrix]"
        "\n        roi: [0, 0, 100, 100]\n    verdict:"
    )
    path = tmp_path / "b" / "cell.yaml"
    path.write_text(text.replace("\n    verdict:", label, 1), encoding="utf-8")
    with pytest.raises(ConfigError) as textual:
        load_config(path)
    assert "'label.text' cannot be sent: it is text" in str(textual.value)


def test_a_value_that_rounds_to_zero_from_below_prints_without_a_sign() -> None:
    assert format_number("steps.part.angle", -0.00017) == "0.0"
    assert format_number("value", -1e-9) == "-1e-09"  # not zero when shown
    assert format_number("u", -0.001) == "0.00"
    assert format_number("angle", -0.1) == "-5.7"
    assert struct.pack(">f", 0.0) != struct.pack(">f", -0.0)  # why the sign matters to a PLC


# ----------------------------------------------------------------------------- caliper


def test_a_caliper_value_out_of_tolerance_reads_rounded_and_in_its_unit(tmp_path: Path) -> None:
    bracket = ROOT / "test_inspections" / "caliper_bracket"
    case = tmp_path / "case"
    case.mkdir()
    inspection = (bracket / "inspection.yaml").read_text(encoding="utf-8")
    (case / "inspection.yaml").write_text(
        inspection + f"images: {bracket / 'images'}\n", encoding="utf-8"
    )
    # nominal.png: the bracket is 12.00 mm wide; 12.5 is out of tolerance
    (case / "expected.yaml").write_text(
        "images:\n  nominal.png: {verdict: pass, value: 12.5}\n", encoding="utf-8"
    )
    report = run_case(case)
    assert report.error is None, report.error
    (problem,) = report.images[0].problems
    match = re.fullmatch(r"value (\d+\.\d+) mm, expected 12\.5 ± 0\.02 mm", problem)
    assert match is not None, problem
    assert len(match[1].split(".")[1]) <= 4  # 0.1 µm: what a person reads
    assert float(match[1]) == pytest.approx(12.0, abs=0.02)


# ----------------------------------------------------------------------------- rejections


def test_a_locate_step_that_finds_nothing_says_why_in_the_result_and_legend(
    tmp_path: Path,
) -> None:
    # a dark disc with 140 of its 360 degrees drawn: Hough proposes it, the edge rays see
    # 40 % of the outline, so the candidate is rejected (score < 0.6)
    image = np.full((120, 160), 200, np.uint8)
    cv2.ellipse(image, (80, 60), (20, 20), 0, 0, 140, 40, -1)
    path = tmp_path / "cell.yaml"
    path.write_text(
        "cameras:\n  qc: {source: request}\n"
        "inspections:\n"
        "  - name: holes\n    type: job\n    camera: qc\n    steps:\n"
        "      - name: hole\n        type: locate\n        roi: [20, 10, 120, 100]\n"
        "        method: circle\n"
        "        circle: {min_radius_px: 15, max_radius_px: 25, polarity: dark}\n",
        encoding="utf-8",
    )
    (job,) = load_config(path).inspections
    assert isinstance(job, JobInspection)
    outcome = job.run(InspectionInput(image), overlay=True)
    assert not outcome.passed
    hole = outcome.data["steps"]["hole"]
    assert hole["count"] == 0
    assert hole["reason"].startswith("found 0, needs 1: candidate at (79.5, 59.5) rejected: ")
    assert "(share of the outline seen) < 0.6" in hole["reason"]
    (rejection,) = hole["rejected"]
    assert (rejection["u"], rejection["v"]) == pytest.approx((79.5, 59.5), abs=1.0)
    # the legend line under the verdict carries it (cut to the image's width)
    step = job.steps[0]
    legend = step.run(image, {}).label
    assert legend.startswith("0 found: found 0, needs 1: candidate at (79.5, 59.5) rejected")
    assert outcome.overlay is not None


# ----------------------------------------------------------------------------- ROI edge


def disc(centre: tuple[float, float], radius: float, blur_px: float) -> np.ndarray:
    """A dark disc (grey 40 on 200), anti-aliased at 1/8 px, blurred by ``blur_px`` (sigma)."""
    image = np.full((160, 200), 200, np.uint8)
    cx, cy = (int(round(c * 8)) for c in centre)
    cv2.circle(image, (cx, cy), int(round(radius * 8)), 40, -1, cv2.LINE_AA, shift=3)
    return cv2.GaussianBlur(image, (0, 0), blur_px) if blur_px else image


@pytest.mark.parametrize("blur_px", [0.0, 2.0])
def test_a_circle_near_its_rois_edges_is_read_whole(blur_px: float) -> None:
    # the disc's outline 2.6 px inside each side of the ROI: the edge rays' flat levels lie
    # beyond the ROI, and the circle must keep its full score and its centre
    image = disc((100.5, 80.5), 20.0, blur_px)
    roi = (78, 58, 45, 45)
    rejected: list[Rejection] = []
    found = locate_circles(
        image, roi=roi, radius_range=(15, 25), polarity="dark", rejected=rejected
    )
    assert [r.reason for r in rejected] == []
    (circle,) = found
    assert circle.score == pytest.approx(1.0, abs=0.05)
    assert (circle.u, circle.v) == pytest.approx((100.5, 80.5), abs=0.05)


def test_a_circle_centred_outside_the_roi_is_still_refused() -> None:
    image = disc((100.5, 80.5), 20.0, 0.0)
    # the ROI holds the disc's right half only: its centre is 3.5 px left of the ROI
    found = locate_circles(image, roi=(104, 50, 40, 60), radius_range=(15, 25), polarity="dark")
    assert found == []


def test_a_fixtured_locate_step_reads_a_circle_near_its_rois_edges(tmp_path: Path) -> None:
    # a part turned 30 degrees: a pin (its frame's origin), a mark along its x axis, and the
    # hole 60 px along it, in an ROI of the part frame whose sides are 2.6-3 px from the
    # hole's outline
    c, s = math.cos(math.radians(30.0)), math.sin(math.radians(30.0))
    pin = (40.0, 50.0)
    hole = (pin[0] + 60.0 * c, pin[1] + 60.0 * s)
    mark = (pin[0] + 130.0 * c, pin[1] + 130.0 * s)
    image = np.full((160, 200), 200, np.uint8)
    for (cx, cy), r in ((pin, 8.0), (hole, 20.0), (mark, 6.0)):
        centre = (int(round(cx * 8)), int(round(cy * 8)))
        cv2.circle(image, centre, int(round(r * 8)), 40, -1, cv2.LINE_AA, shift=3)
    image = cv2.GaussianBlur(image, (0, 0), 1.0)
    path = tmp_path / "cell.yaml"
    path.write_text(
        "cameras:\n  qc: {source: request}\n"
        "inspections:\n"
        "  - name: plate\n    type: job\n    camera: qc\n    steps:\n"
        "      - name: pin\n        type: locate\n        roi: [20, 30, 40, 40]\n"
        "        method: circle\n"
        "        circle: {min_radius_px: 5, max_radius_px: 11, polarity: dark}\n"
        "      - name: mark\n        type: locate\n        roi: [135, 95, 35, 40]\n"
        "        method: circle\n"
        "        circle: {min_radius_px: 4, max_radius_px: 8, polarity: dark}\n"
        "      - name: frame\n        type: fixture\n        origin: pin\n"
        "        x_towards: mark\n"
        "      - name: hole\n        type: locate\n        fixture: frame\n"
        "        roi: [37, -23, 46, 46]\n        method: circle\n"
        "        circle: {min_radius_px: 15, max_radius_px: 25, polarity: dark}\n",
        encoding="utf-8",
    )
    (job,) = load_config(path).inspections
    assert isinstance(job, JobInspection)
    outcome = job.run(InspectionInput(image), overlay=False)
    assert outcome.data["steps"]["frame"]["passed"]
    step = outcome.data["steps"]["hole"]
    assert step["passed"], step.get("reason")
    assert step["score"] == pytest.approx(1.0, abs=0.05)
    assert (step["u"], step["v"]) == pytest.approx(hole, abs=0.1)
