"""The web console's page in a real headless Chromium, against the console API's test double
(tests/helpers/console_stub.py: the real static files, fixed sample answers, every request
recorded). What is checked is the page: navigation, the login page on 401, what the try panel and
the results filter send, and that text from the server is shown as text.

The same page against the real server comes with the server's HTTP front-end.

Screenshots of each page go to a temporary directory, or to ``CONSOLE_SCREENSHOTS``; the ones
docs/console.md shows come from the real server (scripts/console_screenshots.py).
"""

from __future__ import annotations

import os
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any, TypeVar

import pytest
from browser import console_errors, drag_on_image, headless_chromium, save_screenshot
from console_stub import ConsoleStub, Recorded, console_stub

selenium = pytest.importorskip("selenium")
from selenium.common.exceptions import StaleElementReferenceException  # noqa: E402
from selenium.webdriver.common.by import By  # noqa: E402
from selenium.webdriver.remote.webdriver import WebDriver  # noqa: E402
from selenium.webdriver.remote.webelement import WebElement  # noqa: E402
from selenium.webdriver.support.ui import Select, WebDriverWait  # noqa: E402

pytestmark = pytest.mark.slow
T = TypeVar("T")
# Only bounds a hang: every wait below ends as soon as its condition holds.
WAIT_S = 30.0
HOSTILE = '<img src=x onerror="window.__pwned = 1">'


@pytest.fixture(scope="module")
def driver() -> Iterator[WebDriver]:
    with headless_chromium() as d:
        yield d


@pytest.fixture
def shots(tmp_path: Path) -> Path:
    wanted = os.environ.get("CONSOLE_SCREENSHOTS")
    return Path(wanted) if wanted else tmp_path


def wait_for(driver: WebDriver, condition: Callable[[WebDriver], T], what: str) -> T:
    """Wait until ``condition`` is truthy; elements the page re-rendered meanwhile are looked up
    again on the next round (the results table refreshes itself)."""
    wait = WebDriverWait(driver, WAIT_S, ignored_exceptions=(StaleElementReferenceException,))
    return wait.until(condition, f"timed out waiting for {what}")


def row_texts(driver: WebDriver) -> list[str]:
    return list(
        driver.execute_script(
            "return [...document.querySelectorAll('#results-body tr')].map((r) => r.innerText);"
        )
    )


def click(driver: WebDriver, selector: str) -> bool:
    driver.find_element(By.CSS_SELECTOR, selector).click()
    return True


def open_console(driver: WebDriver, stub: ConsoleStub, page: str) -> None:
    driver.delete_all_cookies()
    driver.get(f"{stub.url}/#/{page}")
    console_errors(driver)  # start each test with an empty browser log


def visible_page(driver: WebDriver) -> str:
    return str(
        driver.execute_script(
            "return [...document.querySelectorAll('section.page')]"
            ".filter((s) => !s.hidden).map((s) => s.id).join(',');"
        )
    )


def image_loaded(element: WebElement) -> bool:
    return bool(element.get_property("complete")) and int(element.get_property("naturalWidth")) > 0


def tries(stub: ConsoleStub) -> list[dict[str, Any]]:
    """The JSON ``request`` parts of the try requests the page sent, oldest first."""
    return [
        r.body
        for r in stub.recorded("/api/inspections/magnet_check/try", "POST")
        if isinstance(r.body, dict)
    ]


def results_queries(stub: ConsoleStub) -> list[Recorded]:
    return stub.recorded("/api/results", "GET")


def test_the_nav_switches_pages_without_a_reload(driver: WebDriver, shots: Path) -> None:
    with console_stub() as stub:
        open_console(driver, stub, "cameras")
        qc = wait_for(
            driver,
            lambda d: d.find_element(By.CSS_SELECTOR, "[data-camera=qc] img.camera-image"),
            "the qc camera's card",
        )
        wait_for(driver, lambda d: image_loaded(qc), "the qc camera's live image")
        # The live view changes: the page keeps asking for new frames with fresh queries.
        first = len(stub.recorded("/api/cameras/qc/frame.jpg"))
        wait_for(
            driver,
            lambda d: len(stub.recorded("/api/cameras/qc/frame.jpg")) >= first + 2,
            "two more frames",
        )
        ticks = [r.query.get("t") for r in stub.recorded("/api/cameras/qc/frame.jpg")]
        assert len(set(ticks)) == len(ticks), f"frame requests repeat a query: {ticks}"
        tool = driver.find_element(By.CSS_SELECTOR, "[data-camera=tool] .camera-placeholder")
        wait_for(driver, lambda d: "no image yet" in tool.text, "the request camera's 404 text")
        save_screenshot(driver, shots / "cameras.png")
        driver.execute_script("window.__samePage = true;")

        for name, ready in [
            ("inspections", "#inspection-list [data-inspection=magnet_check]"),
            ("results", "#results-body tr[data-id='120']"),
            ("server", "#srv-identity td"),
            ("cameras", "[data-camera=qc]"),
        ]:
            driver.find_element(By.CSS_SELECTOR, f".nav-link[data-page={name}]").click()
            wait_for(driver, lambda d, n=name: visible_page(d) == f"page-{n}", f"page {name}")
            wait_for(driver, lambda d, s=ready: d.find_elements(By.CSS_SELECTOR, s), ready)
            active = driver.find_element(By.CSS_SELECTOR, ".nav-link.active")
            assert active.get_attribute("data-page") == name
            assert driver.current_url.endswith(f"#/{name}")
            if name == "server":
                assert "0.1.0" in driver.find_element(By.ID, "srv-identity").text
                save_screenshot(driver, shots / "server.png")
        assert driver.execute_script("return window.__samePage === true;"), "the page reloaded"
        assert console_errors(driver) == []


def test_the_login_page_appears_on_401_and_a_good_token_opens_the_console(
    driver: WebDriver, shots: Path
) -> None:
    with console_stub(token="s3cret-token") as stub:
        open_console(driver, stub, "cameras")
        wait_for(driver, lambda d: visible_page(d) == "page-login", "the login page")
        assert not driver.find_element(By.ID, "nav").is_displayed()
        assert stub.recorded("/api/cameras/qc/frame.jpg") == [], "frames asked for before login"
        save_screenshot(driver, shots / "login.png")

        token = driver.find_element(By.ID, "login-token")
        token.send_keys("wrong")
        driver.find_element(By.ID, "login-submit").click()
        error = driver.find_element(By.ID, "login-error")
        wait_for(driver, lambda d: "not valid" in error.text, "the refusal")
        assert visible_page(driver) == "page-login"

        token.clear()
        token.send_keys("s3cret-token")
        driver.find_element(By.ID, "login-submit").click()
        wait_for(driver, lambda d: visible_page(d) == "page-cameras", "the cameras page")
        qc = wait_for(
            driver,
            lambda d: d.find_element(By.CSS_SELECTOR, "[data-camera=qc] img.camera-image"),
            "the qc camera's card",
        )
        wait_for(driver, lambda d: image_loaded(qc), "the qc camera's live image")
        assert [r.body for r in stub.recorded("/api/login")] == [
            {"token": "wrong"},
            {"token": "s3cret-token"},
        ]
        # The session cookie is HttpOnly: the page's scripts cannot read it.
        assert "cellvision_session" not in driver.execute_script("return document.cookie;")
        assert driver.get_cookie("cellvision_session") is not None

        driver.find_element(By.ID, "logout").click()
        wait_for(driver, lambda d: visible_page(d) == "page-login", "the login page again")
        assert console_errors(driver) == []


def test_the_try_panel_sends_the_dragged_roi_and_parameters(driver: WebDriver, shots: Path) -> None:
    with console_stub() as stub:
        open_console(driver, stub, "inspections")
        wait_for(
            driver,
            lambda d: d.find_elements(By.CSS_SELECTOR, "[data-inspection=magnet_check]"),
            "the inspection list",
        )
        driver.find_element(By.CSS_SELECTOR, "[data-inspection=magnet_check]").click()
        config = driver.find_element(By.ID, "insp-config")
        wait_for(driver, lambda d: "dark_fraction" in config.text, "the configuration as loaded")
        assert "roi: [486, 236, 50, 60]" in config.text
        driver.find_element(By.ID, "try-run").click()
        verdict = driver.find_element(By.ID, "try-verdict")
        wait_for(driver, lambda d: verdict.text == "PASS", "the first verdict")
        assert tries(stub)[-1] == {"source": "camera", "options": {}, "overlay": True}
        image = driver.find_element(By.ID, "try-image")
        wait_for(driver, lambda d: image_loaded(image), "the overlay image")
        assert driver.find_elements(By.CSS_SELECTOR, "#try-histogram svg line.threshold")

        # Draw a new ROI away from the magnet: the re-run gets it as options.roi and fails.
        canvas = driver.find_element(By.ID, "try-canvas")
        drag_on_image(driver, canvas, (700, 500), (780, 580))

        def dragged(roi: object) -> bool:
            # One CSS pixel is about 1.6 image pixels at this window size: allow two of them.
            return isinstance(roi, list) and all(
                abs(got - want) <= 4 for got, want in zip(roi, [700, 500, 80, 80], strict=True)
            )

        # A slow machine may re-run mid-drag (the re-run is debounced, not held until the
        # drag ends): wait for the try with the whole drag, whatever came before it.
        wait_for(
            driver,
            lambda d: dragged(tries(stub)[-1]["options"].get("roi")),
            "a try with the dragged ROI [700, 500, 80, 80]",
        )
        roi = tries(stub)[-1]["options"]["roi"]
        assert all(isinstance(v, int) for v in roi), roi
        wait_for(driver, lambda d: verdict.text == "FAIL", "the verdict of the moved ROI")
        snippet = driver.find_element(By.ID, "yaml-snippet").text
        assert snippet.startswith("- name: magnet_check")
        assert f"roi: [{roi[0]}, {roi[1]}, {roi[2]}, {roi[3]}]" in snippet

        # Drag the ROI itself (from inside it) back over the magnet: it moves, keeping its size.
        inside = (roi[0] + roi[2] // 2, roi[1] + roi[3] // 2)
        drag_on_image(driver, canvas, inside, (inside[0] - 200, inside[1] - 250))
        wait_for(
            driver,
            lambda d: tries(stub)[-1]["options"].get("roi", roi)[0] < roi[0] - 150,
            "a try with the moved ROI",
        )
        moved = tries(stub)[-1]["options"]["roi"]
        assert moved[2:] == roi[2:], f"moving changed the size: {roi} -> {moved}"

        # A parameter: the number input re-runs with it in options, beside the ROI.
        threshold = driver.find_element(By.CSS_SELECTOR, "input.param-number[data-param=threshold]")
        threshold.clear()
        threshold.send_keys("120")
        wait_for(
            driver,
            lambda d: tries(stub)[-1]["options"].get("threshold") == 120,
            "a try with threshold 120",
        )
        assert tries(stub)[-1]["options"]["roi"] == moved
        wait_for(driver, lambda d: verdict.text == "PASS", "the verdict over the magnet")
        save_screenshot(driver, shots / "inspections.png")

        # Saving a refused edit shows the validator's message as it came.
        threshold.clear()
        threshold.send_keys("300")
        wait_for(
            driver,
            lambda d: tries(stub)[-1]["options"].get("threshold") == 300,
            "a try with threshold 300",
        )
        driver.find_element(By.ID, "save-config").click()
        driver.find_element(By.ID, "save-why").send_keys("too bright")
        driver.find_element(By.ID, "save-confirm").click()
        refusal = driver.find_element(By.ID, "save-error")
        wait_for(driver, lambda d: refusal.is_displayed(), "the refusal")
        assert "cell.yaml:53: inspections[1].threshold" in refusal.text
        saves = stub.recorded("/api/inspections/magnet_check/save", "POST")
        assert saves[-1].body == {"options": {"roi": moved, "threshold": 300}, "why": "too bright"}
        assert console_errors(driver) == []


def test_the_results_filter_sends_its_query_and_a_row_opens_its_image(
    driver: WebDriver, shots: Path
) -> None:
    with console_stub() as stub:
        open_console(driver, stub, "results")
        wait_for(
            driver,
            lambda d: d.find_elements(By.CSS_SELECTOR, "#results-body tr[data-id='120']"),
            "the newest result",
        )
        first = results_queries(stub)[0].query
        assert first == {"limit": "50"}, first
        wait_for(
            driver,
            lambda d: d.find_elements(By.CSS_SELECTOR, "#f-inspection option[value=magnet_check]"),
            "the inspection filter's choices",
        )
        Select(driver.find_element(By.ID, "f-inspection")).select_by_value("magnet_check")
        Select(driver.find_element(By.ID, "f-verdict")).select_by_value("fail")
        driver.find_element(By.ID, "f-peer").send_keys("10.0.0.8")
        since = "2025-10-09T07:00:00"
        driver.execute_script("document.getElementById('f-since').value = arguments[0];", since)
        since_s = driver.execute_script(
            "return String(Math.floor(new Date(arguments[0]).getTime() / 1000));", since
        )
        driver.find_element(By.ID, "f-apply").click()
        wanted = {
            "inspection": "magnet_check",
            "verdict": "fail",
            "peer": "10.0.0.8",
            "since": since_s,
            "limit": "50",
        }
        wait_for(
            driver,
            lambda d: any(r.query == wanted for r in results_queries(stub)),
            f"a results query {wanted}",
        )
        texts = wait_for(
            driver,
            lambda d: (
                (t := row_texts(d)) and all("magnet_check" in r and "FAIL" in r for r in t) and t
            ),
            "only the filtered rows",
        )
        wait_for(
            driver,
            lambda d: any(
                r.query.get("inspection") == "magnet_check" for r in stub.recorded("/api/stats")
            ),
            "the statistics for the chosen inspection",
        )

        first_id = texts[0].split()[0]
        wait_for(driver, lambda d: click(d, f"#results-body tr[data-id='{first_id}']"), "a row")
        detail = driver.find_element(By.ID, "result-detail")
        wait_for(driver, lambda d: detail.is_displayed(), "the result's detail")
        assert stub.recorded(f"/api/results/{first_id}")
        image = driver.find_element(By.ID, "rd-image")
        wait_for(driver, lambda d: image_loaded(image), "the stored image with its overlay")
        assert image.get_attribute("src").endswith(f"/api/results/{first_id}/image.png?overlay=1")
        assert "FAIL" in driver.find_element(By.ID, "rd-verdict").text
        driver.execute_script("document.querySelector('main').scrollTop = 0;")
        save_screenshot(driver, shots / "results.png")

        # Clear, then page back: the query carries before_id from the previous answer.
        driver.find_element(By.ID, "f-clear").click()
        wait_for(
            driver,
            lambda d: results_queries(stub)[-1].query == {"limit": "50"},
            "the cleared query",
        )
        older = driver.find_element(By.ID, "page-older")
        wait_for(driver, lambda d: older.is_enabled(), "an older page")
        older.click()
        wait_for(
            driver,
            lambda d: results_queries(stub)[-1].query.get("before_id") == "71",
            "the older page's query",
        )
        assert console_errors(driver) == []


def test_text_from_the_server_is_shown_as_text(driver: WebDriver) -> None:
    with console_stub(extra_cameras=[{"name": HOSTILE, "source": "request"}]) as stub:
        open_console(driver, stub, "cameras")
        cards = wait_for(
            driver,
            lambda d: [
                c
                for c in d.find_elements(By.CSS_SELECTOR, ".camera-card")
                if c.get_attribute("data-camera") == HOSTILE
            ],
            "the hostile camera's card",
        )
        assert cards[0].find_element(By.CSS_SELECTOR, ".camera-name").text == HOSTILE
        # No element was made from the name, and its script never ran.
        assert driver.find_elements(By.CSS_SELECTOR, "img[src='x']") == []
        assert driver.execute_script("return window.__pwned === undefined;")
        # Its frame is asked for under its name, encoded into the path.
        wait_for(
            driver,
            lambda d: stub.recorded(f"/api/cameras/{HOSTILE}/frame.jpg"),
            "the hostile camera's frame request",
        )
        assert console_errors(driver) == []
