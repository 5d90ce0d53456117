"""docs/console.md's walkthrough, step by step, in a real browser against the real server: an
integrator tunes ``magnet_check`` from the console alone. Each step asserts what the doc says
the page shows; with ``shots`` a screenshot of every page goes there.

Used by tests/vision_server/test_console_walkthrough.py (the doc stays true) and
scripts/console_screenshots.py (the doc's pictures). Importable as ``console_walkthrough``.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import TypeVar

from browser import console_errors, drag_on_image, save_screenshot
from console_server import TOKEN, RunningConsole
from selenium.common.exceptions import StaleElementReferenceException
from selenium.webdriver.common.by import By
from selenium.webdriver.remote.webdriver import WebDriver
from selenium.webdriver.support.ui import WebDriverWait

T = TypeVar("T")
WAIT_S = 60.0  # only bounds a hang: each wait ends as soon as its condition holds
CONFIGURED_ROI = [486, 236, 50, 60]


def wait_for(driver: WebDriver, condition: Callable[[WebDriver], T], what: str) -> T:
    wait = WebDriverWait(driver, WAIT_S, ignored_exceptions=(StaleElementReferenceException,))
    return wait.until(condition, f"timed out waiting for {what}")


def _text(driver: WebDriver, element_id: str) -> str:
    return str(driver.find_element(By.ID, element_id).text)


def _loaded(driver: WebDriver, element_id: str) -> bool:
    image = driver.find_element(By.ID, element_id)
    return bool(image.get_property("complete")) and int(image.get_property("naturalWidth")) > 0


def _shoot(driver: WebDriver, shots: Path | None, name: str) -> None:
    if shots is not None:
        driver.execute_script("document.querySelector('main').scrollTop = 0;")
        save_screenshot(driver, shots / f"{name}.png")


def _show(driver: WebDriver, server: RunningConsole, page: str) -> None:
    driver.get(f"{server.url}#/{page}")
    wait_for(driver, lambda d: d.find_element(By.ID, f"page-{page}").is_displayed(), page)


def _set_number(driver: WebDriver, selector: str, value: int) -> None:
    """Type ``value`` into a number field as a person would (select all, type)."""
    field = driver.find_element(By.CSS_SELECTOR, selector)
    driver.execute_script("arguments[0].select();", field)
    field.send_keys(str(value))


def walk(driver: WebDriver, server: RunningConsole, shots: Path | None = None) -> None:
    """The walkthrough of docs/console.md, "Tuning magnet_check from the console"."""
    # Sign in.
    driver.delete_all_cookies()
    driver.get(f"{server.url}#/cameras")
    console_errors(driver)
    wait_for(driver, lambda d: d.find_element(By.ID, "login-token").is_displayed(), "sign-in")
    _shoot(driver, shots, "login")
    driver.find_element(By.ID, "login-token").send_keys(TOKEN)
    driver.find_element(By.ID, "login-submit").click()
    wait_for(driver, lambda d: d.find_element(By.ID, "page-cameras").is_displayed(), "cameras")

    # Cameras: the QC camera is live.
    qc = "[data-camera=qc] img.camera-image"
    wait_for(driver, lambda d: d.find_elements(By.CSS_SELECTOR, qc), "the qc camera's card")
    image = driver.find_element(By.CSS_SELECTOR, qc)
    wait_for(driver, lambda d: int(image.get_property("naturalWidth")) > 0, "the live image")
    _shoot(driver, shots, "cameras")

    # 1. Inspections, magnet_check: its configuration as loaded.
    _show(driver, server, "inspections")
    item = "[data-inspection=magnet_check]"
    wait_for(driver, lambda d: d.find_elements(By.CSS_SELECTOR, item), "the inspection list")
    driver.find_element(By.CSS_SELECTOR, item).click()
    wait_for(driver, lambda d: "roi: [486, 236, 50, 60]" in _text(d, "insp-config"), "config")

    # 2. Camera frame, Run: FAIL, dark_fraction 0 (the slot is empty), the histogram beside the
    #    threshold.
    driver.find_element(By.ID, "try-run").click()
    wait_for(driver, lambda d: _text(d, "try-verdict") == "FAIL", "the configured ROI's FAIL")
    wait_for(driver, lambda d: _loaded(d, "try-image"), "the overlay")
    assert "dark_fraction" in _text(driver, "try-values")
    histogram = "#try-histogram svg"
    wait_for(driver, lambda d: d.find_elements(By.CSS_SELECTOR, histogram), "the histogram")
    label = driver.find_element(By.CSS_SELECTOR, f"{histogram} .threshold-label").text
    assert label == "threshold 90", label
    below = driver.find_elements(By.CSS_SELECTOR, f"{histogram} .bar-below")
    assert all(float(b.get_attribute("height") or 0) == 0 for b in below), "dark pixels in ROI"

    # 3. Drag the ROI onto a dark part of the frame: the measure responds, PASS.
    drag_on_image(driver, driver.find_element(By.ID, "try-canvas"), (10, 10), (70, 80))
    wait_for(driver, lambda d: _text(d, "try-verdict") == "PASS", "the dragged ROI's PASS")
    assert "roi:" in _text(driver, "yaml-snippet")
    #    ... and type it back over the slot.
    for field, value in zip(("x", "y", "w", "h"), CONFIGURED_ROI, strict=True):
        _set_number(driver, f"#roi-{field}", value)
    wait_for(driver, lambda d: _text(d, "try-verdict") == "FAIL", "FAIL over the slot again")
    wait_for(driver, lambda d: "roi" not in _text(d, "yaml-snippet"), "no ROI change left")

    # 4. Threshold: the histogram's line follows, the snippet holds the change.
    _set_number(driver, "input.param-number[data-param=threshold]", 100)
    wait_for(
        driver,
        lambda d: (
            d.find_element(By.CSS_SELECTOR, f"{histogram} .threshold-label").text == "threshold 100"
        ),
        "the histogram's threshold at 100",
    )
    wait_for(driver, lambda d: "threshold: 100" in _text(d, "yaml-snippet"), "the snippet")
    _shoot(driver, shots, "inspections")

    # 5. Save: the file is written (backup kept) and the server reloads.
    before = server.app.service.catalog.config_hash
    driver.find_element(By.ID, "save-config").click()
    driver.find_element(By.ID, "save-why").send_keys("threshold 100: the magnet's edge counts")
    driver.find_element(By.ID, "save-confirm").click()
    wait_for(driver, lambda d: "Saved and reloaded" in _text(d, "save-ok"), "the save")
    assert server.app.service.catalog.config_hash != before
    assert "threshold: 100" in server.config.read_text()
    assert list(server.config.parent.glob("cell.yaml.bak-*"))
    wait_for(driver, lambda d: "threshold: 100" in _text(d, "insp-config"), "the reloaded config")

    # 6. Results: the tries are rows (peer "console ..."); the newest opens on its overlay.
    _show(driver, server, "results")
    rows = "#results-body tr"
    wait_for(driver, lambda d: len(d.find_elements(By.CSS_SELECTOR, rows)) >= 3, "the tries")
    newest = driver.find_element(By.CSS_SELECTOR, rows)
    assert "console 127.0.0.1:" in newest.text
    newest.click()
    wait_for(driver, lambda d: _loaded(d, "rd-image"), "the stored overlay")
    assert "overlay=1" in (driver.find_element(By.ID, "rd-image").get_attribute("src") or "")
    card = ".stat-card[data-inspection=magnet_check]"
    wait_for(driver, lambda d: d.find_elements(By.CSS_SELECTOR, card), "magnet_check's stats")
    _shoot(driver, shots, "results")

    # The server page lists the reload.
    _show(driver, server, "server")
    wait_for(driver, lambda d: "APPLIED" in _text(d, "srv-reloads").upper(), "the reload")
    _shoot(driver, shots, "server")

    # Any page added since (each page is a section.page): a picture of it as it opens.
    pages = driver.execute_script(
        "return [...document.querySelectorAll('section.page')].map((s) => s.dataset.page);"
    )
    for page in pages:
        if page and page not in ("login", "cameras", "inspections", "results", "server"):
            _show(driver, server, page)
            _shoot(driver, shots, page)
    assert console_errors(driver) == []
