"""Building inspections on the image, in a real headless Chromium against the real server
(docs/console.md, "Building an inspection on the image"): an integrator builds a fixtured job
from a blank inspection with the page alone (tools drawn on the image, fixtures chosen, offsets
computed by the page), saves it with a why and a robot's INSPECT of the new job passes; a
template is trained in the page; a regex is tested against the inspection's last reads; every
inspection type and step type gets its controls from the schema without a console error.

The job is built on ``test_inspections/fixtured_plate``'s ``moved_a.png`` (the plate moved by
(23.4, -14.7) px and turned by 17 degrees from where the golden job was taught) replayed by a
folder camera: the ROI and the band the page computes in the part frame must be the golden
job's ([44, 12, 12, 12]; centre [75, 0] at pi/2), drawn in the image where the plate lies.
With ``CONSOLE_SCREENSHOTS=docs/console`` the pictures of docs/console.md are taken here.
"""

from __future__ import annotations

import math
import os
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import cv2
import pytest
from browser import console_errors, drag_on_image, headless_chromium, save_screenshot
from console_server import TOKEN, example_config, running_cell

from robot_client import SyncVisionClient

selenium = pytest.importorskip("selenium")
from console_pages import WAIT_S, answer_why, sign_in, wait_for  # noqa: E402
from selenium.webdriver.common.by import By  # noqa: E402
from selenium.webdriver.remote.webdriver import WebDriver  # noqa: E402
from selenium.webdriver.support.ui import Select  # noqa: E402

pytestmark = pytest.mark.slow
REPO = Path(__file__).resolve().parents[2]
PLATE = REPO / "test_inspections" / "fixtured_plate" / "images"
LABELS = REPO / "test_inspections" / "label_codes" / "images"
SIZE = (1440, 900)  # the integrator's laptop: the verdict must be seen without scrolling


@pytest.fixture(scope="module")
def driver() -> Iterator[WebDriver]:
    with headless_chromium() as d:
        inner = d.execute_script("return [window.innerWidth, window.innerHeight];")
        size = d.get_window_size()
        d.set_window_size(size["width"] + SIZE[0] - inner[0], size["height"] + SIZE[1] - inner[1])
        yield d


def shots_dir(tmp_path: Path) -> Path:
    return Path(os.environ.get("CONSOLE_SCREENSHOTS") or tmp_path / "shots")


def build_cell(folder: Path) -> Path:
    """The example cell plus a folder camera replaying the turned plate, an inspection on it
    (a robot's INSPECT gives the console its frame) and a label reader on a request camera."""
    config = example_config(folder)
    text = config.read_text(encoding="utf-8")
    camera = f"  plate:\n    source: folder\n    path: {PLATE}\n    glob: moved_a.png\n"
    camera += "  labels:\n    source: request\n"
    text = text.replace("\ncameras:\n", f"\ncameras:\n{camera}", 1)
    extra = (
        "  - name: plate_seen\n    type: presence\n    camera: plate\n"
        "    measure: mean_intensity\n    min: 0\n"
        "  - name: label\n    type: code\n    camera: labels\n"
        "    symbologies: [code128, datamatrix]\n"
    )
    text = text.replace("\ninspections:\n", f"\ninspections:\n{extra}", 1)
    config.write_text(text, encoding="utf-8")
    return config


def save_small_screenshot(d: WebDriver, path: Path) -> None:
    """The viewport at 900 px wide, its colours cut to 32 levels a channel: the camera's noise
    would otherwise make the PNG three times the ~150 KB a doc's picture may take."""
    save_screenshot(d, path, width=900)
    image = cv2.imread(str(path), cv2.IMREAD_COLOR)
    assert image is not None, path
    cv2.imwrite(str(path), (image // 8) * 8, [cv2.IMWRITE_PNG_COMPRESSION, 9])


# ----------------------------------------------------------------------------- page helpers


def settled(d: WebDriver) -> bool:
    """The outcome shown is the try of the last edit (docs/console.md: data-edit, data-tried)."""
    return bool(
        d.execute_script(
            "const s = document.getElementById('try-stage');"
            "return (s.dataset.edit || '0') === (s.dataset.tried || '') "
            "&& !s.classList.contains('busy');"
        )
    )


def wait_tried(d: WebDriver, what: str) -> str:
    wait_for(d, settled, f"the try after {what}")
    return str(d.find_element(By.ID, "try-verdict").text)


def choose(d: WebDriver, element_id: str, value: str) -> None:
    Select(d.find_element(By.ID, element_id)).select_by_value(value)


def type_into(d: WebDriver, element_id: str, value: str) -> None:
    """Select what the box holds and type over it, as a person does."""
    box = d.find_element(By.ID, element_id)
    d.execute_script("arguments[0].select();", box)
    box.send_keys(value)


def click(d: WebDriver, element_id: str) -> None:
    d.find_element(By.ID, element_id).click()


def pending(d: WebDriver) -> Any:
    """What the page would save (js/inspections.js pendingChange())."""
    return d.execute_script(
        "return import('/static/js/inspections.js').then((m) => m.pendingChange());"
    )


def step(d: WebDriver, name: str) -> dict[str, Any]:
    config = pending(d)["config"]
    return next(s for s in config["steps"] if s["name"] == name)


def add_step(d: WebDriver, kind: str, name: str) -> None:
    choose(d, "step-add-type", kind)
    click(d, "step-add")
    wait_for(d, lambda x: x.find_elements(By.ID, "step-field-name"), f"the new {kind} step")
    type_into(d, "step-field-name", name)
    wait_for(d, lambda x: any(s["name"] == name for s in pending(x)["config"]["steps"]), name)


def new_draft(d: WebDriver, name: str, kind: str, camera: str) -> None:
    click(d, "new-inspection")
    wait_for(
        d,
        lambda x: x.find_elements(By.CSS_SELECTOR, f"#new-camera option[value={camera}]"),
        "cameras",
    )
    d.find_element(By.ID, "new-name").send_keys(name)
    choose(d, "new-type", kind)
    choose(d, "new-camera", camera)
    click(d, "new-create")
    wait_for(d, lambda x: x.find_element(By.ID, "insp-name").text == name, f"the draft {name}")


def image_ready(d: WebDriver) -> bool:
    image = d.find_element(By.ID, "try-image")
    return bool(image.get_property("complete")) and int(image.get_property("naturalWidth")) > 0


def part_to_image(frame: dict[str, float], x: float, y: float) -> tuple[float, float]:
    c, s = math.cos(frame["angle"]), math.sin(frame["angle"])
    return frame["u"] + x * c - y * s, frame["v"] + x * s + y * c


def frame_from_values(d: WebDriver, name: str) -> dict[str, float]:
    """A fixture's frame from the values table of the last try ("u 133.4 · v 105.3 · angle ...")."""
    rows = d.find_elements(By.CSS_SELECTOR, "#try-values tr")
    for row in rows:
        if row.find_element(By.CSS_SELECTOR, "th").text.startswith(f"{name} ("):
            text = row.find_element(By.CSS_SELECTOR, "td").text
            bits = dict(b.split(" ", 1) for b in text.split(" · ")[1:])
            return {k: float(bits[k]) for k in ("u", "v", "angle")}
    raise AssertionError(f"no values of {name} in the try's table")


# ----------------------------------------------------------------------------- the journey


def test_an_integrator_builds_a_fixtured_job_from_a_blank_inspection(
    driver: WebDriver, tmp_path: Path
) -> None:
    d = driver
    shots = shots_dir(tmp_path)
    config = build_cell(tmp_path)
    with running_cell(config) as server:
        robot = SyncVisionClient(
            "127.0.0.1", server.app.port, auth_token=TOKEN, request_timeout_s=WAIT_S
        )
        try:
            # The cell has been running: the folder camera's frame is the last one inspected.
            assert robot.inspect("plate_seen").passed
            sign_in(d, server, "inspections")
            new_draft(d, "plate_job", "job", "plate")
            wait_for(d, image_ready, "the camera's frame in the editor")
            assert d.find_element(By.ID, "insp-draft").is_displayed()
            canvas = d.find_element(By.ID, "try-canvas")

            # 1. The big hole: a dark circle, its radius from a ring drawn on the image
            #    (centre (133.4, 105.3), radius 12, ring +-3: 9..15 px).
            add_step(d, "locate", "big_hole")
            choose(d, "step-field-method", "circle")
            choose(d, "step-field-circle-polarity", "dark")
            type_into(d, "step-field-max_count", "1")
            click(d, "tool-ring")
            type_into(d, "tool-ring-search", "3")
            drag_on_image(d, canvas, (133, 105), (145, 105))
            wait_for(
                d,
                lambda x: step(x, "big_hole").get("circle", {}).get("max_radius_px") == 15,
                "the ring",
            )
            assert step(d, "big_hole")["circle"]["min_radius_px"] == 9
            assert wait_tried(d, "the big hole") == "PASS"

            # 2. The small hole, found in a frame at the big hole: "Add fixture" by choosing the
            #    locate; the ROI drawn in the image is converted into that frame.
            add_step(d, "locate", "small_hole")
            choose(d, "step-field-method", "circle")
            choose(d, "step-field-circle-polarity", "dark")
            type_into(d, "step-field-max_count", "1")
            click(d, "tool-ring")
            type_into(d, "tool-ring-search", "2")
            drag_on_image(d, canvas, (229, 135), (236, 135))
            wait_tried(d, "the small hole's ring")
            click(d, "fixture-add")
            choose(d, "fixture-origin", "big_hole")
            click(d, "fixture-apply")
            wait_for(
                d, lambda x: step(x, "small_hole").get("fixture") == "big_hole_frame", "the fixture"
            )
            wait_tried(d, "the fixture")
            click(d, "tool-roi")
            drag_on_image(d, canvas, (195, 56), (273, 155))
            wait_for(d, lambda x: step(x, "small_hole")["roi"][0] > 40, "the small hole's ROI")
            roi = step(d, "small_hole")["roi"]
            # The big hole is at (133.4, 105.3): the drawn box is (62, -49) from it.
            assert abs(roi[0] - 62) <= 2, roi
            assert abs(roi[1] + 49) <= 2, roi
            assert wait_tried(d, "the small hole's ROI") == "PASS"

            # 3. The magnet: a presence step in the part frame (origin the big hole, x towards
            #    the small hole): its ROI drawn on the pocket where the turned plate has it.
            add_step(d, "presence", "magnet")
            choose(d, "step-field-measure", "dark_fraction")
            type_into(d, "step-field-threshold", "110")
            type_into(d, "step-field-min", "0.6")
            click(d, "fixture-add")
            choose(d, "fixture-origin", "big_hole")
            choose(d, "fixture-x-towards", "small_hole")
            click(d, "fixture-apply")
            frame_name = "big_hole_to_small_hole"
            wait_for(d, lambda x: step(x, "magnet").get("fixture") == frame_name, "the part frame")
            wait_tried(d, "the part frame")
            frame = frame_from_values(d, frame_name)
            assert abs(frame["angle"] - math.radians(17.2)) < 0.01, frame
            # The golden job's pocket, [44, 12, 12, 12] in the part frame, is drawn in the image.
            cu, cv = part_to_image(frame, 49.5, 17.5)
            click(d, "tool-roi")
            drag_on_image(d, canvas, (round(cu - 6), round(cv - 6)), (round(cu + 6), round(cv + 6)))
            wait_for(d, lambda x: step(x, "magnet")["roi"][0] > 20, "the magnet's ROI")
            roi = step(d, "magnet")["roi"]
            assert all(abs(a - b) <= 1 for a, b in zip(roi, [44, 12, 12, 12], strict=True)), roi
            assert wait_tried(d, "the magnet's ROI") == "PASS"
            title = d.find_element(By.ID, "target-title").get_attribute("textContent") or ""
            assert "part frame of big_hole_to_small_hole" in title, title

            # 4. The plate's width: a caliper step in the same frame (chosen in its fixture
            #    list), its band drawn across the plate from A to B.
            add_step(d, "caliper", "gauge")
            choose(d, "step-field-fixture", frame_name)
            wait_for(
                d, lambda x: step(x, "gauge").get("fixture") == frame_name, "the gauge's frame"
            )
            click(d, "tool-band")
            type_into(d, "tool-band-width", "6")
            a = part_to_image(frame, 75, -50)
            b = part_to_image(frame, 75, 50)
            drag_on_image(d, canvas, (round(a[0]), round(a[1])), (round(b[0]), round(b[1])))
            wait_for(d, lambda x: step(x, "gauge").get("measurements"), "the band's measurement")
            m = step(d, "gauge")["measurements"][0]
            assert m["kind"] == "width"
            assert abs(m["band"]["center"][0] - 75) <= 1.5, m
            assert abs(m["band"]["center"][1]) <= 1.5, m
            assert abs(m["band"]["angle_rad"] - math.pi / 2) < 0.03, m
            assert abs(m["band"]["length"] - 100) <= 2, m
            assert m["band"]["width"] == 6, m
            type_into(d, "meas-field-name", "plate_width")
            type_into(d, "meas-field-min", "79")
            type_into(d, "meas-field-max", "81")
            assert wait_tried(d, "the gauge's tolerance") == "PASS"

            # 5. The verdict: a wrong name is refused by the try with its column, beside the box.
            type_into(
                d, "insp-field-verdict", "all(big_hole, small_hole, gauge) and magnet.vlue >= 0.6"
            )
            assert wait_tried(d, "a wrong verdict") == "ERROR"
            error = d.find_element(
                By.CSS_SELECTOR, "#param-fields .field-error[data-error-for=verdict]"
            )
            assert "column 38" in error.text, error.text
            assert "vlue" in error.text, error.text
            type_into(
                d, "insp-field-verdict", "all(big_hole, small_hole, gauge) and magnet.value >= 0.6"
            )
            assert wait_tried(d, "the verdict") == "PASS"
            wait_for(d, lambda x: error.text == "", "the verdict's error gone")

            # The verdict is seen whole without scrolling at 1440x900, large.
            verdict = d.find_element(By.ID, "try-verdict")
            d.execute_script("document.querySelector('main').scrollTop = 0;")
            top, bottom, height, font = d.execute_script(
                "const r = arguments[0].getBoundingClientRect();"
                "const font = parseFloat(getComputedStyle(arguments[0]).fontSize);"
                "return [r.top, r.bottom, innerHeight, font];",
                verdict,
            )
            assert top >= 0, (top, bottom, height)
            assert bottom <= height, (top, bottom, height)
            assert font >= 32, font
            save_small_screenshot(d, shots / "build-job.png")

            # 6. Save, with a why: the job is created, listed, and a robot's INSPECT passes.
            click(d, "save-config")
            answer_why(d, "plate job taught on the turned plate")
            ok = d.find_element(By.ID, "save-ok")
            wait_for(d, lambda x: "Saved and reloaded" in ok.text, "the save")
            assert "plate_job created" in ok.text
            item = "#inspection-list [data-inspection=plate_job]"
            wait_for(
                d, lambda x: "draft" not in x.find_element(By.CSS_SELECTOR, item).text, "listed"
            )
            assert not d.find_element(By.ID, "insp-draft").is_displayed()
            assert "plate_job" in config.read_text(encoding="utf-8")
            result = robot.inspect("plate_job")
            assert result.passed, result.data
            assert result.data["steps"]["magnet"]["passed"] is True
            assert 79 <= result.data["steps"]["gauge"]["plate_width"] <= 81
            assert console_errors(d) == []
        finally:
            robot.close()


def test_a_template_is_trained_in_the_page(driver: WebDriver, tmp_path: Path) -> None:
    d = driver
    config = build_cell(tmp_path)
    with running_cell(config) as server:
        robot = SyncVisionClient(
            "127.0.0.1", server.app.port, auth_token=TOKEN, request_timeout_s=WAIT_S
        )
        try:
            assert robot.inspect("plate_seen").passed  # the folder camera's frame
        finally:
            robot.close()
        sign_in(d, server, "inspections")
        # The turned plate's pocket and small hole, cut as a template and found again.
        new_draft(d, "plate_locate", "locate", "plate")
        wait_for(d, image_ready, "the plate camera's frame")
        choose(d, "insp-field-method", "template")
        click(d, "tool-template")
        drag_on_image(d, d.find_element(By.ID, "try-canvas"), (160, 95), (250, 165))
        train = d.find_element(By.ID, "train-template")
        wait_for(d, lambda x: train.is_enabled(), "Train template")
        train.click()
        preview = d.find_element(By.ID, "template-preview")
        wait_for(
            d,
            lambda x: preview.is_displayed() and int(preview.get_property("naturalWidth")) > 0,
            "the crop",
        )
        path = pending(d)["config"]["template"]["image"]
        assert path.startswith("templates/plate_locate-"), path
        assert path.endswith(".png"), path
        crop = cv2.imread(str(tmp_path / path), cv2.IMREAD_UNCHANGED)
        assert crop is not None, path
        assert crop.ndim == 2, crop.shape
        assert abs(crop.shape[1] - 90) <= 3, crop.shape
        assert abs(crop.shape[0] - 70) <= 3, crop.shape
        assert int(preview.get_property("naturalWidth")) == crop.shape[1]
        assert path in d.find_element(By.ID, "template-path").text
        assert wait_tried(d, "the trained template") == "PASS"
        values = d.find_element(By.ID, "try-values").text
        assert "count" in values, values
        # A draft keeps its edits while another inspection is shown.
        d.find_element(By.CSS_SELECTOR, "[data-inspection=magnet_check]").click()
        wait_for(d, lambda x: x.find_element(By.ID, "insp-name").text == "magnet_check", "other")
        d.find_element(By.CSS_SELECTOR, "[data-inspection=plate_locate]").click()
        wait_for(d, lambda x: x.find_element(By.ID, "insp-name").text == "plate_locate", "back")
        assert pending(d)["config"]["template"]["image"] == path
        assert console_errors(d) == []


def test_a_regex_is_tested_against_the_last_reads(driver: WebDriver, tmp_path: Path) -> None:
    d = driver
    config = build_cell(tmp_path)
    with running_cell(config) as server:
        robot = SyncVisionClient(
            "127.0.0.1", server.app.port, auth_token=TOKEN, request_timeout_s=WAIT_S
        )
        try:
            # Production reads of the label reader: a Code 128 and a DataMatrix.
            for name in ("code128.png", "datamatrix.png"):
                image = cv2.imread(str(LABELS / name), cv2.IMREAD_GRAYSCALE)
                assert robot.inspect("label", image).passed
        finally:
            robot.close()
        sign_in(d, server, "inspections")
        item = "[data-inspection=label]"
        wait_for(d, lambda x: x.find_elements(By.CSS_SELECTOR, item), "the list")
        d.find_element(By.CSS_SELECTOR, item).click()
        box_selector = "#param-fields .field-row[data-kind=regex] input"
        wait_for(d, lambda x: x.find_elements(By.CSS_SELECTOR, box_selector), "the regex box")
        box = d.find_element(By.CSS_SELECTOR, box_selector)
        summary = "#param-fields [data-test=regex-summary]"

        def summary_text(x: WebDriver) -> str:
            found = x.find_elements(By.CSS_SELECTOR, summary)
            return str(found[0].text) if found else ""

        box.send_keys(r"ABC\x1d\d+")
        wait_for(d, lambda x: summary_text(x) == "1 of 2 last reads match", "one read matching")
        marks = d.find_elements(By.CSS_SELECTOR, "#param-fields .read")
        assert sorted(m.get_attribute("data-match") for m in marks) == ["no", "yes"]
        matching = next(m for m in marks if m.get_attribute("data-match") == "yes")
        assert "ABC" in matching.text
        # Python's named groups are taken (translated for the check).
        d.execute_script("arguments[0].select();", box)
        box.send_keys(r"(?P<head>.{3})(?P=head)?.*")
        wait_for(d, lambda x: summary_text(x) == "2 of 2 last reads match", "both reads matching")
        d.execute_script("arguments[0].select();", box)
        box.send_keys("((")
        error = d.find_element(
            By.CSS_SELECTOR, "#param-fields .field-row[data-kind=regex] .field-error"
        )
        wait_for(d, lambda x: "does not compile" in error.text, "the compile error")
        assert console_errors(d) == []


def test_every_type_and_step_type_gets_its_controls_from_the_schema(
    driver: WebDriver, tmp_path: Path
) -> None:
    d = driver
    config = build_cell(tmp_path)
    with running_cell(config) as server:
        sign_in(d, server, "inspections")
        schema = d.execute_script(
            "return fetch('/api/schema', {credentials: 'same-origin'}).then((r) => r.json());"
        )
        assert set(schema["types"]) >= {
            "presence",
            "locate",
            "qr",
            "code",
            "qr_pose",
            "caliper",
            "calibration_board",
            "job",
        }
        for kind in schema["types"]:
            new_draft(d, f"draft_{kind}", kind, "qc")
            rows = d.find_elements(By.CSS_SELECTOR, "#param-fields .field-row")
            shown = {r.get_attribute("data-field") for r in rows}
            assert shown, kind
            # Every key that always applies has its control (the ROI, lists and the name are
            # drawn elsewhere).
            for key in schema["common"] + schema["types"][kind]["keys"]:
                if (
                    key.get("when")
                    or key["kind"] in ("roi", "list")
                    or key["key"] in ("name", "type")
                ):
                    continue
                assert key["key"] in shown, (kind, key["key"])
            # An enum's choices, each shown: the keys of its method appear, the others' go.
            for key in schema["types"][kind]["keys"]:
                if key["kind"] == "enum" and not key.get("when"):
                    for value in key["values"]:
                        choose(d, f"insp-field-{key['key'].replace('.', '-')}", str(value))
            if kind == "job":
                for step_type in schema["steps"]:
                    choose(d, "step-add-type", step_type)
                    click(d, "step-add")
                    wait_for(
                        d,
                        lambda x, t=step_type: (
                            f"({t})"
                            in (
                                x.find_element(By.ID, "step-title").get_attribute("textContent")
                                or ""
                            )
                        ),
                        f"the {step_type} step's controls",
                    )
                    names = {
                        r.get_attribute("data-field")
                        for r in d.find_elements(By.CSS_SELECTOR, "#step-fields .field-row")
                    }
                    for key in schema["steps"][step_type]["keys"]:
                        if (
                            key.get("when")
                            or key["kind"] in ("roi", "list")
                            or key["key"] == "type"
                        ):
                            continue
                        assert key["key"] in names, (step_type, key["key"])
                wait_for(
                    d, lambda x: len(pending(x)["config"]["steps"]) == len(schema["steps"]), "steps"
                )
        assert console_errors(d) == []


def test_an_existing_inspection_changes_its_measure_and_is_saved_whole(
    driver: WebDriver, tmp_path: Path
) -> None:
    d = driver
    config = build_cell(tmp_path)
    with running_cell(config) as server:
        sign_in(d, server, "inspections")
        item = "[data-inspection=magnet_check]"
        wait_for(d, lambda x: x.find_elements(By.CSS_SELECTOR, item), "the list")
        d.find_element(By.CSS_SELECTOR, item).click()
        wait_for(d, lambda x: x.find_elements(By.ID, "insp-field-threshold"), "its controls")
        # Another measure: the threshold (dark_fraction's) goes, with its value.
        choose(d, "insp-field-measure", "mean_intensity")
        wait_for(d, lambda x: not x.find_elements(By.ID, "insp-field-threshold"), "no threshold")
        assert "threshold" not in pending(d)["config"]
        type_into(d, "insp-field-min", "0")
        type_into(d, "insp-field-max", "255")
        assert wait_tried(d, "the new measure") == "PASS"
        assert "mean_intensity" in d.find_element(By.ID, "try-values").text
        assert "measure: mean_intensity" in d.find_element(By.ID, "yaml-snippet").text
        click(d, "save-config")
        answer_why(d, "the slot's mean grey instead")
        ok = d.find_element(By.ID, "save-ok")
        wait_for(d, lambda x: "Saved and reloaded" in ok.text, "the save")
        saved = d.find_element(By.ID, "insp-config")
        wait_for(d, lambda x: "mean_intensity" in saved.text, "the configuration as loaded")
        assert "threshold" not in saved.text
        text = config.read_text(encoding="utf-8")
        assert '"mean_intensity"' in text
        assert "# Quality control (paper, Table 2)" in text  # the file's comments stay
        assert console_errors(d) == []


def test_a_new_job_on_a_camera_without_a_frame_is_drawn_on_an_upload(
    driver: WebDriver, tmp_path: Path
) -> None:
    """A folder camera nothing has read has no frame to show, and a new job is refused until
    its steps' required keys are set (some by drawing): the uploaded image is shown all the
    same, so that the tools draw on it, and the ring then makes the refused try pass."""
    d = driver
    with running_cell(build_cell(tmp_path)) as server:
        sign_in(d, server, "inspections")
        new_draft(d, "fresh_job", "job", "plate")
        add_step(d, "locate", "hole")
        choose(d, "step-field-method", "circle")
        d.find_element(By.CSS_SELECTOR, "input[name=try-source][value=upload]").click()
        d.find_element(By.ID, "try-file").send_keys(str(PLATE / "moved_a.png"))
        wait_for(d, image_ready, "the uploaded image shown though the try is refused")
        assert d.find_element(By.ID, "try-verdict").text.strip().upper() == "ERROR"
        assert "circle" in d.find_element(By.ID, "try-error").text
        # The ring drawn on the uploaded image sets the radii the try was refused without.
        choose(d, "step-field-circle-polarity", "dark")
        type_into(d, "step-field-max_count", "1")
        click(d, "tool-ring")
        type_into(d, "tool-ring-search", "3")
        drag_on_image(d, d.find_element(By.ID, "try-canvas"), (133, 105), (145, 105))
        wait_for(
            d,
            lambda x: step(x, "hole").get("circle", {}).get("max_radius_px") == 15,
            "the ring",
        )
        assert wait_tried(d, "the ring on the upload") == "PASS"
        assert not console_errors(d)
