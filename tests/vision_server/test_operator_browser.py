"""The Operator page in a real headless Chromium (1280x800) against the real server with the
example cell: a robot client posts an operator call with the failing inspection's overlay, the
page shows it with a badge on the tab, a tap on "Retry" answers it and the robot gets "retry".
With ``CONSOLE_SCREENSHOTS=docs/console`` the page's screenshot replaces docs/console/operator.png.
"""

from __future__ import annotations

import os
from collections.abc import Iterator
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import pytest
from browser import console_errors, headless_chromium, save_screenshot
from console_server import TOKEN, console_server

from protocol import ImageRole
from robot_client import SyncVisionClient

selenium = pytest.importorskip("selenium")
from console_pages import WAIT_S, wait_for  # noqa: E402
from selenium.webdriver.common.by import By  # noqa: E402
from selenium.webdriver.remote.webdriver import WebDriver  # noqa: E402

pytestmark = pytest.mark.slow


@pytest.fixture(scope="module")
def driver() -> Iterator[WebDriver]:
    with headless_chromium() as d:
        yield d


def test_a_call_appears_and_a_tap_on_retry_answers_the_robot(
    driver: WebDriver, tmp_path: Path
) -> None:
    shots = Path(os.environ.get("CONSOLE_SCREENSHOTS") or tmp_path)
    with console_server(tmp_path) as server, ThreadPoolExecutor(max_workers=1) as pool:
        robot = SyncVisionClient(
            "127.0.0.1", server.app.port, auth_token=TOKEN, request_timeout_s=WAIT_S
        )
        try:
            driver.delete_all_cookies()
            driver.get(f"{server.url}#/operator")
            console_errors(driver)
            wait_for(driver, lambda d: d.find_element(By.ID, "login-token").is_displayed(), "login")
            driver.find_element(By.ID, "login-token").send_keys(TOKEN)
            driver.find_element(By.ID, "login-submit").click()
            empty = driver.find_element(By.ID, "operator-empty")
            wait_for(driver, lambda d: empty.is_displayed(), "the empty Operator page")
            badge = driver.find_element(By.ID, "operator-badge")
            assert not badge.is_displayed()

            # The paper's quality control: magnet_check fails, the robot calls the operator
            # with the failing image's overlay.
            result = robot.inspect("magnet_check", overlay=True)
            overlay = next(i for i in result.images if i.role is ImageRole.OVERLAY)
            asked = pool.submit(
                robot.operator_call,
                "inspection 'magnet_check' failed 3 time(s): magnet missing",
                inspection="magnet_check",
                skill="quality_control",
                images=(overlay,),
                deadline_s=600.0,
            )
            card = wait_for(
                driver, lambda d: d.find_element(By.CSS_SELECTOR, "article.operator-call"), "call"
            )
            assert "magnet missing" in card.text
            assert "quality_control · magnet_check" in card.text
            image = card.find_element(By.CSS_SELECTOR, "img.operator-image")
            wait_for(
                driver,
                lambda d: (
                    image.get_property("complete")
                    and int(image.get_property("naturalWidth")) == overlay.width
                ),
                "the overlay image",
            )
            wait_for(driver, lambda d: badge.is_displayed() and badge.text == "1", "the badge")
            buttons = card.find_elements(By.CSS_SELECTOR, "button.btn-choice")
            assert [b.text for b in buttons] == ["Retry", "Continue", "Abort"]
            # Big enough for a finger on the cell's 1280x800 touch screen.
            assert all(b.size["height"] >= 64 and b.size["width"] >= 150 for b in buttons)
            wait_for(
                driver,
                lambda d: "waiting" in card.text and "gives up in" in card.text,
                "the waiting time",
            )
            save_screenshot(driver, shots / "operator.png")
            assert not asked.done()

            buttons[0].click()
            answer = asked.result(WAIT_S)
            assert answer.choice == "retry"
            assert answer.by.startswith("admin (console 127.0.0.1:")
            wait_for(driver, lambda d: empty.is_displayed(), "the call gone from the page")
            wait_for(driver, lambda d: not badge.is_displayed(), "the badge gone")
            status = driver.find_element(By.ID, "operator-status")
            assert "answered Retry" in status.text
            assert console_errors(driver) == []
        finally:
            robot.close()
