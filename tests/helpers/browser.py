"""A real headless Chromium for the browser tests: Debian's ``chromium`` driven through its own
``chromedriver`` by selenium, with a 1280x800 window (the cell's touch screen).

``scripts/browser_setup.sh`` installs both when they are missing and it can (root, apt-get); where
it cannot, the tests are skipped with its one-line reason. Nothing is downloaded: the driver and
the browser are given by path, so selenium-manager never looks for them on the network.

Importable as ``browser`` (pytest's ``pythonpath`` includes tests/helpers).
"""

from __future__ import annotations

import contextlib
import functools
import os
import subprocess
import tempfile
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import pytest

if TYPE_CHECKING:  # selenium is imported lazily: a missing package skips the test, not errors
    from selenium.webdriver.remote.webdriver import WebDriver
    from selenium.webdriver.remote.webelement import WebElement

REPO_ROOT = Path(__file__).resolve().parents[2]
SETUP = REPO_ROOT / "scripts" / "browser_setup.sh"
SKIP_STATUS = 77  # browser_setup.sh: cannot run here, the reason on stderr
WINDOW = (1280, 800)


@dataclass(frozen=True)
class BrowserPaths:
    chromium: str
    chromedriver: str


@functools.cache
def _setup() -> tuple[int, str, str]:
    """Run the set-up script once per test session: (exit status, stdout, stderr)."""
    try:
        done = subprocess.run(
            ["bash", str(SETUP)], capture_output=True, text=True, timeout=900, check=False
        )
    except (OSError, subprocess.TimeoutExpired) as exc:
        return SKIP_STATUS, "", f"browser_setup: could not run {SETUP}: {exc}"
    return done.returncode, done.stdout, done.stderr


def browser_paths() -> BrowserPaths:
    """Chromium and chromedriver, installed if needed; skips the test where that cannot be."""
    status, out, err = _setup()
    reason = err.strip().splitlines()[-1] if err.strip() else f"exit status {status}"
    if status == SKIP_STATUS:
        pytest.skip(reason)
    if status != 0:
        raise AssertionError(f"{SETUP} failed ({status}): {err.strip()}")
    found = dict(line.split("=", 1) for line in out.splitlines() if "=" in line)
    return BrowserPaths(chromium=found["chromium"], chromedriver=found["chromedriver"])


@contextlib.contextmanager
def headless_chromium() -> Iterator[WebDriver]:
    """A WebDriver on a fresh headless Chromium profile, closed on exit."""
    paths = browser_paths()
    try:
        from selenium import webdriver
        from selenium.webdriver.chrome.service import Service
    except ImportError:
        pytest.skip("selenium is not installed (it is in the test extra: pip install -e '.[test]')")
    # selenium-manager would otherwise try to download a browser or driver it thinks is missing.
    os.environ["SE_OFFLINE"] = "true"
    with tempfile.TemporaryDirectory(prefix="cellvision-chromium-") as profile:
        options = webdriver.ChromeOptions()
        options.binary_location = paths.chromium
        for arg in (
            "--headless=new",
            "--no-sandbox",  # the tests run as root in containers
            "--disable-dev-shm-usage",
            "--disable-gpu",
            f"--window-size={WINDOW[0]},{WINDOW[1]}",
            f"--user-data-dir={profile}",
            "--no-first-run",
            "--disable-extensions",
            "--disable-background-networking",
            "--disable-component-update",
            "--disable-sync",
            "--hide-scrollbars",
            "--force-device-scale-factor=1",
        ):
            options.add_argument(arg)
        options.set_capability("goog:loggingPrefs", {"browser": "ALL"})
        service = Service(executable_path=paths.chromedriver, log_output=subprocess.DEVNULL)
        driver = webdriver.Chrome(service=service, options=options)
        try:
            # Headless windows count the browser's frame; make the page itself 1280x800.
            inner = driver.execute_script("return [window.innerWidth, window.innerHeight];")
            if tuple(inner) != WINDOW:
                size = driver.get_window_size()
                driver.set_window_size(
                    size["width"] + WINDOW[0] - inner[0], size["height"] + WINDOW[1] - inner[1]
                )
            yield driver
        finally:
            driver.quit()


def save_screenshot(driver: WebDriver, path: Path, *, width: int = 1024) -> Path:
    """Save the viewport as a PNG scaled to ``width`` pixels (small enough to commit)."""
    import cv2
    import numpy as np

    png = driver.get_screenshot_as_png()
    image = cv2.imdecode(np.frombuffer(png, np.uint8), cv2.IMREAD_COLOR)
    if image is None:
        raise AssertionError("the browser's screenshot is not a PNG")
    if image.shape[1] > width:
        height = round(image.shape[0] * width / image.shape[1])
        image = cv2.resize(image, (width, height), interpolation=cv2.INTER_AREA)
    path.parent.mkdir(parents=True, exist_ok=True)
    if not cv2.imwrite(str(path), image, [cv2.IMWRITE_PNG_COMPRESSION, 9]):
        raise AssertionError(f"could not write {path}")
    return path


def console_errors(driver: WebDriver) -> list[str]:
    """The browser console's errors since the last call: script errors, not the HTTP errors the
    page expects and handles (a 404 frame, a 401 before signing in)."""
    return [
        e["message"]
        for e in driver.get_log("browser")
        if e.get("level") == "SEVERE" and "Failed to load resource" not in e["message"]
    ]


def drag_on_image(
    driver: WebDriver, canvas: WebElement, start: tuple[int, int], end: tuple[int, int]
) -> None:
    """Drag on the console's ROI canvas between two points given in image pixels (u, v) of the
    try image (Selenium 4 offsets are from the element's centre, in CSS pixels)."""
    from selenium.webdriver.common.action_chains import ActionChains

    scale, width, height = driver.execute_script(
        "const i = document.getElementById('try-image');"
        "return [i.naturalWidth / i.clientWidth, i.clientWidth, i.clientHeight];"
    )

    def offset(point: tuple[int, int]) -> tuple[int, int]:
        return round(point[0] / scale - width / 2), round(point[1] / scale - height / 2)

    x0, y0 = offset(start)
    x1, y1 = offset(end)
    actions = ActionChains(driver)
    actions.move_to_element_with_offset(canvas, x0, y0).click_and_hold()
    actions.move_by_offset((x1 - x0) // 2, (y1 - y0) // 2)
    actions.move_by_offset(x1 - x0 - (x1 - x0) // 2, y1 - y0 - (y1 - y0) // 2).release()
    actions.perform()
