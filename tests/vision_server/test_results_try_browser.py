"""The Results page's "Try this image" and "Export CSV" in real headless Chromium against the
real server with the example cell: a stored failure is tried again from its row without typing
its id, and the export link carries exactly the filters shown (the CSV itself:
tests/vision_server/test_results_export.py).
"""

from __future__ import annotations

import time
from collections.abc import Iterator
from pathlib import Path
from urllib.parse import parse_qs, urlsplit

import numpy as np
import pytest
from browser import console_errors, headless_chromium
from console_server import Browserless, RunningConsole, console_server

from vision_server.results import ResultEntry

selenium = pytest.importorskip("selenium")
from console_pages import sign_in, wait_for  # noqa: E402
from selenium.webdriver.common.by import By  # noqa: E402
from selenium.webdriver.remote.webdriver import WebDriver  # noqa: E402
from selenium.webdriver.support.ui import Select  # noqa: E402

pytestmark = pytest.mark.slow


@pytest.fixture(scope="module")
def driver() -> Iterator[WebDriver]:
    with headless_chromium() as d:
        yield d


@pytest.fixture
def server(tmp_path: Path) -> Iterator[RunningConsole]:
    with console_server(tmp_path) as running:
        yield running


def stored(server: RunningConsole, image: np.ndarray | None, *, passed: bool) -> int:
    """A production row of magnet_check with ``image`` as its stored input (None: none)."""
    log = server.app.service.results
    assert log is not None
    row = log.record(
        ResultEntry(
            time=time.time(),
            inspection="magnet_check",
            camera="qc",
            passed=passed,
            data={},
            duration_ms=1.0,
            config_hash="earlier",
            peer="10.0.0.7:41000",
            image=image,
        )
    )
    assert row is not None
    return row


def open_row(driver: WebDriver, row: int) -> None:
    wait_for(
        driver,
        lambda d: d.find_elements(By.CSS_SELECTOR, f"#results-body tr[data-id='{row}']"),
        f"row {row}",
    )
    driver.find_element(By.CSS_SELECTOR, f"#results-body tr[data-id='{row}']").click()
    wait_for(driver, lambda d: d.find_element(By.ID, "result-detail").is_displayed(), "detail")


def test_a_stored_result_is_tried_again_from_its_row(
    driver: WebDriver, server: RunningConsole
) -> None:
    # magnet_check passes on a dark slot and fails on a bright one (examples/cell.yaml: the
    # dark fraction of its ROI at threshold 90 against min 0.25): two stored inputs, each of
    # which must give its own verdict when tried again.
    dark = np.full((768, 1024, 3), 20, np.uint8)
    bright = np.full((768, 1024, 3), 230, np.uint8)
    dark_row = stored(server, dark, passed=False)
    bright_row = stored(server, bright, passed=False)  # the log keeps failures' images
    bare = Browserless(server.url)
    assert bare.login().status == 200
    no_image = bare.try_("magnet_check", {"source": "camera"}).json()  # a try: no stored input
    assert no_image["verdict"] in ("pass", "fail")

    sign_in(driver, server, "results")
    for row, verdict in ((dark_row, "PASS"), (bright_row, "FAIL")):
        driver.get(server.url + "#/results")
        open_row(driver, row)
        button = driver.find_element(By.ID, "rd-try")
        wait_for(driver, lambda d, b=button: b.is_displayed(), "Try this image")
        button.click()
        wait_for(
            driver,
            lambda d: d.find_element(By.ID, "page-inspections").is_displayed(),
            "the Inspections page",
        )
        wait_for(
            driver,
            lambda d: d.find_element(By.ID, "insp-name").text == "magnet_check",
            "magnet_check opened",
        )
        assert driver.find_element(By.ID, "try-result-id").get_property("value") == str(row)
        assert driver.find_element(
            By.CSS_SELECTOR, "input[name=try-source][value=result]"
        ).is_selected()
        wait_for(
            driver,
            lambda d, v=verdict: d.find_element(By.ID, "try-verdict").text.strip().upper() == v,
            f"the try on result {row}: {verdict}",
        )
        # The stored result is taken once: the hash names the inspection only.
        assert driver.execute_script("return location.hash") == "#/inspections/magnet_check"
    assert not console_errors(driver)


def test_a_row_without_a_stored_input_offers_no_try(
    driver: WebDriver, server: RunningConsole
) -> None:
    row = stored(server, None, passed=True)
    sign_in(driver, server, "results")
    open_row(driver, row)
    assert not driver.find_element(By.ID, "rd-try").is_displayed()


def test_the_export_link_carries_the_filters_shown(
    driver: WebDriver, server: RunningConsole
) -> None:
    sign_in(driver, server, "results")
    wait_for(
        driver,
        lambda d: d.find_elements(By.CSS_SELECTOR, "#f-inspection option[value=magnet_check]"),
        "the inspection filter's choices",
    )
    Select(driver.find_element(By.ID, "f-inspection")).select_by_value("magnet_check")
    Select(driver.find_element(By.ID, "f-verdict")).select_by_value("fail")
    driver.find_element(By.ID, "f-operator").send_keys("anna")
    driver.find_element(By.ID, "f-apply").click()

    def query(d: WebDriver) -> dict[str, list[str]]:
        href = d.find_element(By.ID, "results-export").get_attribute("href") or ""
        return parse_qs(urlsplit(href).query)

    wanted = {"inspection": ["magnet_check"], "verdict": ["fail"], "operator": ["anna"]}
    wait_for(driver, lambda d: query(d) == wanted, "the export link's filters")
    href = driver.find_element(By.ID, "results-export").get_attribute("href") or ""
    assert urlsplit(href).path == "/api/results.csv"


def test_an_inspection_is_opened_by_its_address(driver: WebDriver, server: RunningConsole) -> None:
    sign_in(driver, server, "cameras")
    driver.get(server.url + "#/inspections/cap_locate")
    driver.refresh()
    wait_for(
        driver,
        lambda d: d.find_element(By.ID, "insp-name").text == "cap_locate",
        "cap_locate opened by its address",
    )
    driver.find_element(By.CSS_SELECTOR, "#inspection-list [data-inspection=magnet_check]").click()
    wait_for(
        driver,
        lambda d: d.execute_script("return location.hash") == "#/inspections/magnet_check",
        "the address to follow the inspection chosen",
    )
