"""The console page in real headless Chromium against the real server with the example cell
(tests/helpers/console_server.py): sign in, the live image, a try whose dragged ROI changes
the verdict, and a saved edit that reloads the server."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import pytest
from browser import console_errors, drag_on_image, headless_chromium
from console_server import console_server

selenium = pytest.importorskip("selenium")
from console_pages import sign_in, wait_for  # noqa: E402
from selenium.webdriver.common.by import By  # noqa: E402
from selenium.webdriver.remote.webdriver import WebDriver  # noqa: E402
from selenium.webdriver.remote.webelement import WebElement  # noqa: E402

pytestmark = pytest.mark.slow


@pytest.fixture(scope="module")
def driver() -> Iterator[WebDriver]:
    with headless_chromium() as d:
        yield d


def image_loaded(element: WebElement) -> bool:
    return bool(element.get_property("complete")) and int(element.get_property("naturalWidth")) > 0


def test_live_view_and_a_dragged_roi_changes_the_verdict_and_saves(
    driver: WebDriver, tmp_path: Path
) -> None:
    with console_server(tmp_path) as server:
        sign_in(driver, server, "cameras")
        qc = wait_for(
            driver,
            lambda d: d.find_element(By.CSS_SELECTOR, "[data-camera=qc] img.camera-image"),
            "the qc camera's card",
        )
        wait_for(driver, lambda d: image_loaded(qc), "the qc camera's live image")
        first = qc.get_attribute("src")
        wait_for(driver, lambda d: qc.get_attribute("src") != first, "the live image to change")

        driver.get(f"{server.url}#/inspections")
        wait_for(
            driver,
            lambda d: d.find_elements(By.CSS_SELECTOR, "[data-inspection=magnet_check]"),
            "the inspection list",
        )
        driver.find_element(By.CSS_SELECTOR, "[data-inspection=magnet_check]").click()
        driver.find_element(By.ID, "try-run").click()
        verdict = driver.find_element(By.ID, "try-verdict")
        wait_for(driver, lambda d: verdict.text == "FAIL", "the configured ROI's verdict")
        image = driver.find_element(By.ID, "try-image")
        wait_for(driver, lambda d: image_loaded(image), "the overlay")
        # A dark corner of the scene: dark_fraction well above min, so PASS.
        drag_on_image(driver, driver.find_element(By.ID, "try-canvas"), (10, 10), (70, 80))
        wait_for(driver, lambda d: verdict.text == "PASS", "the dragged ROI's verdict")

        before = server.app.service.catalog.config_hash
        driver.find_element(By.ID, "save-config").click()
        # A save asks why (kept with the version of the file).
        driver.find_element(By.ID, "save-why").send_keys("the magnet check on the dark corner")
        driver.find_element(By.ID, "save-confirm").click()
        ok = driver.find_element(By.ID, "save-ok")
        wait_for(driver, lambda d: "Saved and reloaded" in ok.text, "the save")
        assert server.app.service.catalog.config_hash != before
        assert "roi: [" in server.config.read_text()
        assert list(tmp_path.glob("cell.yaml.bak-*"))
        assert console_errors(driver) == []
