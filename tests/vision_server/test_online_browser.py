"""The online view in a real headless Chromium against the real server with the example cell: a
robot client runs inspections through the protocol; the Cameras page draws each inspection's
last graphics and verdict over its camera's image (read back from the canvas's pixels) and
shows counts and strips equal to the results sent (console tries left out); the toggles hide
the graphics; "Reset all counts" zeroes them; the wall screen (#/online) at 1920x1080 needs no
mouse. With ``CONSOLE_SCREENSHOTS=docs/console`` it refreshes docs/console/online.png and
docs/console/online-wall.png."""

from __future__ import annotations

import math
import os
import textwrap
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pytest
from browser import console_errors, headless_chromium, save_screenshot
from console_server import TOKEN, Browserless, console_server, running_cell

from robot_client import SyncVisionClient

selenium = pytest.importorskip("selenium")
from console_pages import WAIT_S, sign_in, visible_page, wait_for  # noqa: E402
from selenium.webdriver.common.by import By  # noqa: E402
from selenium.webdriver.common.keys import Keys  # noqa: E402
from selenium.webdriver.remote.webdriver import WebDriver  # noqa: E402

pytestmark = pytest.mark.slow

CASES = Path(__file__).resolve().parents[2] / "test_inspections"
FAIL_RGB = (0xFF, 0x44, 0x38)
PASS_RGB = (0x2F, 0xD6, 0x6B)
FEATURE_RGB = (0x00, 0xE5, 0xFF)

# The canvas's pixels and where the image lies under it (CSS px = canvas px at scale 1).
CANVAS_JS = """
const card = document.querySelector(
  `section.page:not([hidden]) article.camera-card[data-camera="${arguments[0]}"]`);
const canvas = card.querySelector("canvas.online-canvas");
const image = card.querySelector("img.camera-image");
const ctx = canvas.getContext("2d");
const data = ctx.getImageData(0, 0, canvas.width, canvas.height).data;
return {width: canvas.width, height: canvas.height, pixels: Array.from(data),
        view: [canvas.clientWidth, canvas.clientHeight],
        natural: [image.naturalWidth, image.naturalHeight], drawn: canvas.dataset.drawn,
        boxes: canvas.dataset.verdictBoxes};
"""


@pytest.fixture(scope="module")
def driver() -> Iterator[WebDriver]:
    with headless_chromium() as d:
        yield d


class Canvas:
    """One camera card's canvas, read back: RGB pixels and the image-to-screen mapping."""

    def __init__(self, raw: dict[str, Any]) -> None:
        self.rgb = np.array(raw["pixels"], np.uint8).reshape(raw["height"], raw["width"], 4)[
            :, :, :3
        ]
        self.drawn = str(raw["drawn"] or "")
        width, height = raw["view"]
        nw, nh = raw["natural"]
        self.ready = nw > 0 and nh > 0
        """Whether the live image has loaded (the graphics are drawn over it then)."""
        nw, nh = (nw, nh) if self.ready else (width, height)
        self.fit = min(width / nw, height / nh)
        self.left = (width - nw * self.fit) / 2
        self.top = (height - nh * self.fit) / 2
        boxes = str(raw["boxes"] or "").split(";")
        self.boxes = [tuple(int(v) for v in box.split(",")) for box in boxes if box]
        """Each verdict box drawn: (left, top, right, bottom), CSS px."""

    def screen(self, u: float, v: float) -> tuple[int, int]:
        return round(self.left + (u + 0.5) * self.fit), round(self.top + (v + 0.5) * self.fit)

    def has(
        self, colour: tuple[int, int, int], x: int, y: int, r: int = 3, *, tolerance: int = 12
    ) -> bool:
        """Whether a pixel near (x, y) has ``colour`` (within ``tolerance`` grey levels)."""
        patch = self.rgb[max(y - r, 0) : y + r + 1, max(x - r, 0) : x + r + 1].astype(int)
        return bool((np.abs(patch - np.array(colour)).max(axis=2) <= tolerance).any())

    def extent(self, colour: tuple[int, int, int], box: tuple[int, int, int, int]) -> int:
        """Rows (px) from the first to the last of ``colour``'s pixels in ``box`` (x0, y0, x1,
        y1): how tall the text in that colour is."""
        x0, y0, x1, y1 = box
        patch = self.rgb[y0:y1, x0:x1].astype(int)
        rows = np.nonzero((np.abs(patch - np.array(colour)).max(axis=2) <= 12).any(axis=1))[0]
        return int(rows[-1] - rows[0] + 1) if rows.size else 0


def _canvas(driver: WebDriver, camera: str) -> Canvas:
    return Canvas(driver.execute_script(CANVAS_JS, camera))


def _row(driver: WebDriver, camera: str, inspection: str) -> Any:
    wall = "wall-" if visible_page(driver) == "page-online" else ""
    return driver.find_element(By.ID, f"{wall}online-{camera}-{inspection}")


def _counts(driver: WebDriver, camera: str, inspection: str) -> dict[str, str]:
    row = _row(driver, camera, inspection)
    return {
        key: row.find_element(By.CSS_SELECTOR, f'[data-test="count-{key}"]').text
        for key in ("pass", "fail", "yield", "total")
    }


def _strip(driver: WebDriver, camera: str, inspection: str) -> list[tuple[str, str]]:
    cells = _row(driver, camera, inspection).find_elements(By.CSS_SELECTOR, ".strip-cell")
    return [(c.get_attribute("data-verdict"), c.get_attribute("data-result-id")) for c in cells]


def _caps() -> np.ndarray:
    image = np.full((768, 1024), 40, np.uint8)
    cv2.circle(image, (300, 300), 80, 230, -1)
    cv2.circle(image, (700, 420), 70, 230, -1)
    return image


def _inner_size(driver: WebDriver, width: int, height: int) -> None:
    """Make the page itself ``width`` x ``height`` (the window counts its frame)."""
    driver.set_window_size(width, height)
    inner = driver.execute_script("return [window.innerWidth, window.innerHeight];")
    size = driver.get_window_size()
    driver.set_window_size(size["width"] + width - inner[0], size["height"] + height - inner[1])


def test_the_cameras_page_draws_each_inspections_last_result_and_counts_them(
    driver: WebDriver, tmp_path: Path
) -> None:
    shots = Path(os.environ.get("CONSOLE_SCREENSHOTS") or tmp_path)
    with console_server(tmp_path) as server:
        robot = SyncVisionClient(
            "127.0.0.1", server.app.port, auth_token=TOKEN, request_timeout_s=WAIT_S
        )
        try:
            # The cell's production: magnet_check fails three times (the empty slot),
            # cap_locate fails once and passes twice (the last result shows two caps).
            for _ in range(3):
                assert not robot.inspect("magnet_check").passed
            assert not robot.inspect("cap_locate", np.full((768, 1024), 40, np.uint8)).passed
            for _ in range(2):
                assert robot.inspect("cap_locate", _caps()).passed
            # An integrator's try that passes is not production: not counted, not drawn.
            api = Browserless(server.url)
            api.login()
            tried = api.try_("magnet_check", {"source": "camera", "options": {"min": 0.0}})
            assert tried.json()["verdict"] == "pass"
            rows = api.get("/api/results?inspection=magnet_check&limit=20").json()["results"]
            magnet_ids = sorted(str(r["id"]) for r in rows if not r["try"])

            _inner_size(driver, 1280, 800)
            sign_in(driver, server, "cameras")
            wait_for(
                driver,
                lambda d: _counts(d, "qc", "magnet_check")["total"] == "3",
                "magnet_check's counts",
            )
            assert _counts(driver, "qc", "magnet_check") == {
                "pass": "0",
                "fail": "3",
                "yield": "0.0 %",
                "total": "3",
            }
            assert _strip(driver, "qc", "magnet_check") == [("fail", i) for i in magnet_ids]
            wait_for(
                driver,
                lambda d: _counts(d, "tool", "cap_locate")["total"] == "3",
                "cap_locate's counts",
            )
            assert _counts(driver, "tool", "cap_locate") == {
                "pass": "2",
                "fail": "1",
                "yield": "66.7 %",
                "total": "3",
            }
            assert [v for v, _ in _strip(driver, "tool", "cap_locate")] == [
                "fail",
                "pass",
                "pass",
            ]
            verdict = _row(driver, "qc", "magnet_check").find_element(
                By.CSS_SELECTOR, '[data-test="last-verdict"]'
            )
            assert verdict.text == "FAIL"

            # The graphics, read back from the canvas: magnet_check's ROI in red where the
            # configuration puts it ([486, 236, 50, 60]), and its verdict in large red type.
            def drawn_on_qc(d: WebDriver) -> Canvas | None:
                canvas = _canvas(d, "qc")
                return canvas if canvas.ready and canvas.drawn == "magnet_check" else None

            qc = wait_for(driver, drawn_on_qc, "magnet_check's graphics on the qc camera")
            for u, v in ((511, 235.5), (485.5, 266), (535.5, 266)):  # top, left, right edges
                assert qc.has(FAIL_RGB, *qc.screen(u, v)), (u, v)
            assert not qc.has(FAIL_RGB, *qc.screen(300, 600), 6)  # nothing elsewhere
            # The verdict: one box, placed off the ROI, its word in red about 34 px tall.
            (box,) = qc.boxes
            roi_x, roi_y = qc.screen(511, 266)
            assert not (box[0] <= roi_x <= box[2] and box[1] <= roi_y <= box[3])
            tall = qc.extent(FAIL_RGB, (box[0] + 6, box[1] + 6, box[0] + 90, box[3] - 6))
            assert tall >= 22, f"the FAIL verdict is {tall} px tall: too small to read far off"

            tool = wait_for(
                driver,
                lambda d: c if (c := _canvas(d, "tool")).ready and c.drawn else None,
                "cap_locate's graphics",
            )
            assert tool.drawn == "cap_locate"
            for (u, v), r in (((300, 300), 80), ((700, 420), 70)):
                assert tool.has(FEATURE_RGB, *tool.screen(u, v)), "the centre's marker"
                assert tool.has(FEATURE_RGB, *tool.screen(u + r, v)), "the circle's edge"
            (box,) = tool.boxes
            assert tool.extent(PASS_RGB, (box[0] + 6, box[1] + 6, box[0] + 90, box[3] - 6)) >= 22
            assert console_errors(driver) == []
            save_screenshot(driver, shots / "online.png")

            # The card's toggle hides every graphic of that camera, the inspection's its own.
            driver.find_element(By.ID, "overlay-toggle-qc").click()
            hidden = wait_for(
                driver, lambda d: (c := _canvas(d, "qc")).drawn == "" and c, "hidden graphics"
            )
            assert not hidden.has(FAIL_RGB, *hidden.screen(511, 236))
            driver.find_element(By.ID, "overlay-toggle-qc").click()
            wait_for(driver, lambda d: _canvas(d, "qc").drawn == "magnet_check", "shown again")
            driver.find_element(By.ID, "overlay-qc-magnet_check").click()
            wait_for(driver, lambda d: _canvas(d, "qc").drawn == "", "magnet_check hidden")
            driver.find_element(By.ID, "overlay-qc-magnet_check").click()
            wait_for(driver, lambda d: _canvas(d, "qc").drawn == "magnet_check", "and shown")

            # Reset: every count to zero; the next result counts from there, unreloaded.
            driver.find_element(By.ID, "online-reset-all").click()
            wait_for(
                driver,
                lambda d: (
                    _counts(d, "qc", "magnet_check")["total"] == "0"
                    and _counts(d, "tool", "cap_locate")["total"] == "0"
                ),
                "the counts reset",
            )
            assert _strip(driver, "qc", "magnet_check") == []
            robot.inspect("magnet_check")
            wait_for(
                driver,
                lambda d: _counts(d, "qc", "magnet_check")["fail"] == "1",
                "the next result counted",
            )
            robot.inspect("cap_locate", _caps())

            # The wall screen at 1920x1080: no top bar, large counts, keys only.
            _inner_size(driver, 1920, 1080)
            driver.get(f"{server.url}#/online")
            wait_for(driver, lambda d: visible_page(d) == "page-online", "the wall screen")
            assert not driver.find_element(By.CSS_SELECTOR, "header.topbar").is_displayed()
            wall = driver.find_element(By.ID, "online-cards")
            wait_for(
                driver,
                lambda d: len(wall.find_elements(By.CSS_SELECTOR, "article.camera-card")) == 3,
                "every camera on the wall",
            )
            wait_for(
                driver,
                lambda d: (c := _canvas(d, "qc")).ready and c.drawn == "magnet_check",
                "the wall's graphics over the live image",
            )
            wait_for(driver, lambda d: _counts(d, "tool", "cap_locate")["pass"] == "1", "counts")
            value = _row(driver, "qc", "magnet_check").find_element(
                By.CSS_SELECTOR, '[data-test="count-fail"]'
            )
            assert float(value.value_of_css_property("font-size").removesuffix("px")) >= 32
            qc_wall = _canvas(driver, "qc")
            (box,) = qc_wall.boxes
            word = (box[0] + 8, box[1] + 8, box[0] + 150, box[3] - 8)
            assert qc_wall.extent(FAIL_RGB, word) >= 36
            assert console_errors(driver) == []
            save_screenshot(driver, shots / "online-wall.png", width=1280)
            # "3" shows the third camera alone, "0" every camera, Escape leaves the wall.
            body = driver.find_element(By.TAG_NAME, "body")
            body.send_keys("3")
            wait_for(
                driver,
                lambda d: (
                    [
                        c.get_attribute("data-camera")
                        for c in wall.find_elements(By.CSS_SELECTOR, "article.camera-card")
                    ]
                    == ["qc"]
                ),
                "the qc camera alone",
            )
            assert driver.execute_script("return location.hash") == "#/online/qc"
            body.send_keys("0")
            wait_for(
                driver,
                lambda d: len(wall.find_elements(By.CSS_SELECTOR, "article.camera-card")) == 3,
                "every camera again",
            )
            body.send_keys(Keys.ESCAPE)
            wait_for(driver, lambda d: visible_page(d) == "page-cameras", "the Cameras page")
            assert driver.find_element(By.CSS_SELECTOR, "header.topbar").is_displayed()
            assert console_errors(driver) == []
        finally:
            robot.close()
            _inner_size(driver, 1280, 800)


def test_an_operator_sees_the_counts_and_no_reset(driver: WebDriver, tmp_path: Path) -> None:
    operator = "online-operator-tablet-token"
    with console_server(tmp_path, operator_token=operator) as server:
        robot = SyncVisionClient(
            "127.0.0.1", server.app.port, auth_token=TOKEN, request_timeout_s=WAIT_S
        )
        try:
            robot.inspect("magnet_check")
            sign_in(driver, server, "cameras", token=operator)
            wait_for(
                driver,
                lambda d: _counts(d, "qc", "magnet_check")["fail"] == "1",
                "the operator's counts",
            )
            assert not driver.find_element(By.ID, "online-reset-all").is_displayed()
            reset = _row(driver, "qc", "magnet_check").find_element(
                By.CSS_SELECTOR, '[data-test="reset-inspection"]'
            )
            assert not reset.is_displayed()
            assert driver.find_element(By.ID, "overlay-toggle-qc").is_displayed()
            assert console_errors(driver) == []
        finally:
            robot.close()


def _plate_cell(folder: Path) -> Path:
    """A cell of one request camera and test_inspections/fixtured_plate's job on it."""
    case = (CASES / "fixtured_plate" / "inspection.yaml").read_text(encoding="utf-8")
    job = case[case.index("inspection:\n") + len("inspection:\n") :]
    config = folder / "cell.yaml"
    config.write_text(
        "server:\n  host: 127.0.0.1\n  port: 0\n  name: plate-cell\n"
        f"  auth_token: {TOKEN}\n"
        "console: {enabled: true, host: 127.0.0.1, port: 0}\n"
        "cameras:\n  qc:\n    source: request\n"
        "    intrinsics: {width: 320, height: 240, fx: 400, fy: 400, cx: 159.5, cy: 119.5}\n"
        "inspections:\n  -" + textwrap.indent(job, "  ")[3:],
        encoding="utf-8",
    )
    return config


def test_a_fixtured_jobs_roi_is_drawn_turned_with_the_part(
    driver: WebDriver, tmp_path: Path
) -> None:
    """The magnet's ROI [44, 12, 12, 12] in the part's frame, drawn where
    docs/configuration.md's formula puts it for the part's pose in this image."""
    image = cv2.imread(str(CASES / "fixtured_plate" / "images" / "moved_b.png"))
    with running_cell(_plate_cell(tmp_path)) as server:
        robot = SyncVisionClient(
            "127.0.0.1", server.app.port, auth_token=TOKEN, request_timeout_s=WAIT_S
        )
        try:
            result = robot.inspect("plate_magnet", image)
            assert result.passed
            part = result.data["steps"]["part"]
            # on the wall screen, the camera alone: the 320x240 image about 1000 px wide
            _inner_size(driver, 1920, 1080)
            sign_in(driver, server, "online")
            driver.execute_script("location.hash = '#/online/qc';")
            wall = driver.find_element(By.ID, "online-cards")
            wait_for(
                driver,
                lambda d: len(wall.find_elements(By.CSS_SELECTOR, "article.camera-card")) == 1,
                "the qc camera alone on the wall",
            )
            qc = wait_for(
                driver,
                lambda d: c if (c := _canvas(d, "qc")).ready and c.drawn else None,
                "the job's graphics",
            )
            assert qc.drawn == "plate_magnet"
            assert qc.fit > 2.5
            c, s = math.cos(part["angle"]), math.sin(part["angle"])
            # the middle of each side of the ROI's outline (pixel edges: 43.5 .. 55.5)
            for x, y in ((49.5, 11.5), (55.5, 17.5), (49.5, 23.5), (43.5, 17.5)):
                u = part["u"] + x * c - y * s
                v = part["v"] + x * s + y * c
                assert qc.has(PASS_RGB, *qc.screen(u, v), 3, tolerance=40), (x, y)
            assert not qc.has(
                PASS_RGB,
                *qc.screen(part["u"] + 49.5 * c - 17.5 * s, part["v"] + 49.5 * s + 17.5 * c),
                3,
            )
            # the part frame's x axis, red, from the big hole towards the small one
            tip = qc.screen(part["u"] + 20 * c, part["v"] + 20 * s)
            assert qc.has(FAIL_RGB, *tip, 3, tolerance=40)
            assert console_errors(driver) == []
        finally:
            robot.close()
