"""The History journey in real headless Chromium against the real server with the example cell
(docs/console.md, "History"): an integrator saves a changed ROI with a reason, opens History,
sees who, when and why with the diff, reverts with one click and a confirmation, and a try then
runs the old value again.

With ``CONSOLE_SCREENSHOTS=docs/console`` the page's screenshot replaces docs/console/history.png.
"""

from __future__ import annotations

import os
from collections.abc import Iterator
from pathlib import Path

import pytest
from browser import console_errors, drag_on_image, headless_chromium, save_screenshot
from console_server import console_server

selenium = pytest.importorskip("selenium")
from console_pages import answer_why, sign_in, visible_page, wait_for  # noqa: E402
from selenium.webdriver.common.by import By  # noqa: E402
from selenium.webdriver.remote.webdriver import WebDriver  # noqa: E402

pytestmark = pytest.mark.slow
INTEGRATOR = "integrator-test-token-0123456789"
OPERATOR = "operator-test-token-0123456789"


@pytest.fixture(scope="module")
def driver() -> Iterator[WebDriver]:
    with headless_chromium() as d:
        yield d


def _text(driver: WebDriver, element_id: str) -> str:
    return str(driver.find_element(By.ID, element_id).text)


def _run_magnet_check(driver: WebDriver) -> str:
    """Open magnet_check on the Inspections page, run it on the camera frame; its verdict."""
    wait_for(
        driver,
        lambda d: d.find_elements(By.CSS_SELECTOR, "[data-inspection=magnet_check]"),
        "the inspection list",
    )
    driver.find_element(By.CSS_SELECTOR, "[data-inspection=magnet_check]").click()
    wait_for(driver, lambda d: _text(d, "insp-name") == "magnet_check", "magnet_check opened")
    driver.find_element(By.ID, "try-verdict")
    driver.execute_script("document.getElementById('try-verdict').textContent = '—';")
    driver.find_element(By.ID, "try-run").click()
    return str(
        wait_for(
            driver,
            lambda d: _text(d, "try-verdict") in ("PASS", "FAIL") and _text(d, "try-verdict"),
            "the try's verdict",
        )
    )


def test_save_with_a_why_then_see_the_diff_and_revert_in_one_click(
    driver: WebDriver, tmp_path: Path
) -> None:
    shots = Path(os.environ.get("CONSOLE_SCREENSHOTS") or tmp_path)
    with console_server(tmp_path, integrator_token=INTEGRATOR, operator_token=OPERATOR) as server:
        original = server.config.read_text()
        original_hash = server.app.service.catalog.config_hash
        sign_in(driver, server, "inspections", token=INTEGRATOR)
        assert _run_magnet_check(driver) == "FAIL"  # the empty slot
        # A dark corner of the scene: PASS; saved with a reason.
        drag_on_image(driver, driver.find_element(By.ID, "try-canvas"), (10, 10), (70, 80))
        wait_for(driver, lambda d: _text(d, "try-verdict") == "PASS", "the dragged ROI's PASS")
        driver.find_element(By.ID, "save-config").click()
        # Cancelling the question saves nothing.
        wait_for(driver, lambda d: d.find_element(By.ID, "why-dialog").is_displayed(), "why")
        driver.find_element(By.ID, "why-cancel").click()
        assert server.config.read_text() == original
        driver.find_element(By.ID, "save-config").click()
        answer_why(driver, "ROI moved to the dark corner for the trial run")
        wait_for(driver, lambda d: "Saved and reloaded" in _text(d, "save-ok"), "the save")
        assert "version 2" in _text(driver, "save-ok")
        saved_hash = server.app.service.catalog.config_hash
        assert saved_hash != original_hash

        # History: the save on top (who, why, what), the file as found below it.
        driver.find_element(By.ID, "nav-history").click()
        wait_for(driver, lambda d: visible_page(d) == "page-history", "the History page")
        row = wait_for(driver, lambda d: d.find_element(By.ID, "history-row-2"), "version 2")
        assert "integrator" in row.text
        assert "ROI moved to the dark corner for the trial run" in row.text
        assert "magnet_check" in row.text
        assert "The file as found" in _text(driver, "history-row-1")
        row.click()
        wait_for(driver, lambda d: _text(d, "hd-title") == "Version 2", "version 2's detail")
        added = [e.text for e in driver.find_elements(By.CSS_SELECTOR, "#hd-diff .diff-add")]
        removed = [e.text for e in driver.find_elements(By.CSS_SELECTOR, "#hd-diff .diff-del")]
        assert any(line.startswith("+") and "roi:" in line for line in added), added
        assert any(line == "-    roi: [486, 236, 50, 60]" for line in removed), removed
        assert "integrator" in _text(driver, "hd-meta")
        # The file holds version 2: reverting to it would change nothing.
        assert driver.find_element(By.ID, "history-revert").get_property("disabled")
        save_screenshot(driver, shots / "history.png")

        # One click on version 1, Revert, confirmed with a reason.
        driver.find_element(By.ID, "history-row-1").click()
        wait_for(driver, lambda d: _text(d, "hd-title") == "Version 1", "version 1's detail")
        driver.find_element(By.ID, "history-revert").click()
        answer_why(driver, "back to the magnet slot")
        wait_for(
            driver,
            lambda d: "Reverted to version 1: saved as version 3" in _text(d, "history-status"),
            "the revert",
        )
        assert server.config.read_text() == original
        assert server.app.service.catalog.config_hash == original_hash
        row = wait_for(driver, lambda d: d.find_element(By.ID, "history-row-3"), "version 3")
        assert "Revert to version 1" in row.text
        assert "back to the magnet slot" in row.text

        # The server runs the old ROI again: the empty slot fails.
        driver.get(f"{server.url}#/inspections")
        wait_for(driver, lambda d: visible_page(d) == "page-inspections", "Inspections")
        assert _run_magnet_check(driver) == "FAIL"
        assert console_errors(driver) == []


def test_an_operator_sees_the_history_but_no_revert(driver: WebDriver, tmp_path: Path) -> None:
    with console_server(tmp_path, integrator_token=INTEGRATOR, operator_token=OPERATOR) as server:
        from console_server import Browserless

        integrator = Browserless(server.url)
        assert integrator.login(INTEGRATOR).status == 200
        saved = integrator.post_json(
            "/api/inspections/magnet_check/save",
            {"options": {"threshold": 100}, "why": "darker magnets"},
        )
        assert saved.status == 200, saved.body
        sign_in(driver, server, "history", token=OPERATOR)
        row = wait_for(driver, lambda d: d.find_element(By.ID, "history-row-2"), "version 2")
        assert "darker magnets" in row.text
        row.click()
        wait_for(driver, lambda d: _text(d, "hd-title") == "Version 2", "version 2's detail")
        assert not driver.find_element(By.ID, "history-revert").is_displayed()
        assert console_errors(driver) == []
