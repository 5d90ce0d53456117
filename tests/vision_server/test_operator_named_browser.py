"""A named operator answers a robot's call with a reason, in a real headless Chromium against
the real server (the example cell with named users, console on port 0) and a real robot client
running the quality_control skill.

On an 800x1280 tablet in portrait: anna signs in with her name and PIN, the header shows her
name and does not overlap itself; the robot's quality_control fails magnet_check and calls the
operator naming the failed result; anna taps Continue, is asked for a reason (a preset or typed)
and then for a confirmation, and confirms. The robot gets the choice, her name and the reason;
the result's row carries them, and ``/api/results?operator=anna`` finds it. Then on a 1920x1080
wall screen: a second call, large buttons, answered with Retry (no reason asked). The header is
checked at 1440x900 too; after Log out, a badge reader's token and Enter sign ben in. With
``CONSOLE_SCREENSHOTS=docs/console`` the pictures of docs/console.md are taken on the way
(operator-tablet.png, operator-reason.png, operator-wall.png, login-named.png).
"""

from __future__ import annotations

import os
from collections.abc import Iterator
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Any

import pytest
from browser import console_errors, headless_chromium, save_screenshot
from console_server import TOKEN, Browserless, running_cell
from console_users import ANNA_PIN, BEN_BADGE, PRESETS, config_with_users

from protocol import ImageRole
from robot_client import SyncVisionClient
from robot_client.devices.sim import sim_devices
from robot_client.operator import ConsoleOperator
from robot_client.skills import SkillContext, default_registry, execute
from simulation import SimCell

selenium = pytest.importorskip("selenium")
from console_pages import WAIT_S, wait_for  # noqa: E402
from selenium.webdriver.common.by import By  # noqa: E402
from selenium.webdriver.remote.webdriver import WebDriver  # noqa: E402

pytestmark = pytest.mark.slow

SCENE = Path(__file__).resolve().parents[2] / "examples/scenes/grundfos_cell.yaml"
TYPED = "scratch on the flange is cosmetic"


@pytest.fixture(scope="module")
def driver() -> Iterator[WebDriver]:
    with headless_chromium() as d:
        yield d


def viewport(driver: WebDriver, width: int, height: int) -> None:
    """Make the page itself ``width`` x ``height`` CSS pixels."""
    driver.set_window_size(width, height)
    inner = driver.execute_script("return [window.innerWidth, window.innerHeight];")
    size = driver.get_window_size()
    driver.set_window_size(size["width"] + width - inner[0], size["height"] + height - inner[1])
    wait_for(
        driver,
        lambda d: (
            d.execute_script("return [window.innerWidth, window.innerHeight];") == [width, height]
        ),
        f"a {width}x{height} viewport",
    )


def header_overlaps(driver: WebDriver) -> list[str]:
    """Pairs of the header's parts (brand, nav, status) whose boxes intersect, and parts that
    stick out of the viewport."""
    found = driver.execute_script(
        """
        const parts = ['.topbar .brand', '#nav', '.topbar .status'].map((s) => [s,
          document.querySelector(s).getBoundingClientRect()]);
        const out = [];
        for (let i = 0; i < parts.length; i++) {
          const [a, ra] = parts[i];
          if (ra.right > window.innerWidth + 0.5 || ra.left < -0.5) out.push(a + ' outside');
          for (let j = i + 1; j < parts.length; j++) {
            const [b, rb] = parts[j];
            const x = Math.min(ra.right, rb.right) - Math.max(ra.left, rb.left);
            const y = Math.min(ra.bottom, rb.bottom) - Math.max(ra.top, rb.top);
            if (x > 0.5 && y > 0.5) out.push(a + ' / ' + b);
          }
        }
        return out;
        """
    )
    return list(found)


def test_a_named_operator_answers_with_a_reason_on_a_tablet_and_a_wall_screen(
    driver: WebDriver, tmp_path: Path
) -> None:
    shots = Path(os.environ.get("CONSOLE_SCREENSHOTS") or tmp_path)
    config = config_with_users(tmp_path)
    with running_cell(config) as server, ThreadPoolExecutor(max_workers=1) as pool:
        robot = SyncVisionClient(
            "127.0.0.1", server.app.port, auth_token=TOKEN, request_timeout_s=WAIT_S
        )
        try:
            viewport(driver, 800, 1280)
            driver.delete_all_cookies()
            driver.get(f"{server.url}#/operator")
            console_errors(driver)
            wait_for(driver, lambda d: d.find_element(By.ID, "login-user").is_displayed(), "login")
            driver.find_element(By.ID, "login-user").send_keys("anna")
            driver.find_element(By.ID, "login-pin").send_keys("0000")
            driver.find_element(By.ID, "login-submit").click()
            error = driver.find_element(By.ID, "login-error")
            wait_for(driver, lambda d: "do not match" in error.text, "the wrong PIN refused")
            driver.find_element(By.ID, "login-pin").send_keys(ANNA_PIN)
            save_screenshot(driver, shots / "login-named.png", width=560)
            driver.find_element(By.ID, "login-submit").click()
            empty = driver.find_element(By.ID, "operator-empty")
            wait_for(driver, lambda d: empty.is_displayed(), "the empty Operator page")
            who = driver.find_element(By.ID, "signed-in-user")
            wait_for(driver, lambda d: who.text == "anna", "anna's name in the header")
            assert driver.find_element(By.ID, "signed-in-role").text == "operator"
            assert header_overlaps(driver) == []

            # The robot's quality_control: magnet_check fails (no magnet), the skill calls the
            # operator at the console with the failed result's id and its overlay.
            notes: list[str] = []
            ctx = SkillContext.create(sim_devices(SimCell.from_yaml(SCENE), vision=robot))
            ctx.operator = ConsoleOperator(robot, None, deadline_s=120.0, notify=notes.append)
            skill = default_registry().get("quality_control")
            record = skill.teach("magnet", {"inspection": "magnet_check", "retries": 0}, ctx)
            running = pool.submit(execute, skill, record, ctx)

            card = wait_for(
                driver, lambda d: d.find_element(By.CSS_SELECTOR, "article.operator-call"), "call"
            )
            assert "magnet_check" in card.text
            assert "FAIL" in card.text
            image = card.find_element(By.CSS_SELECTOR, "img.operator-image")
            wait_for(driver, lambda d: image.get_property("complete"), "the overlay image")
            buttons = card.find_elements(By.CSS_SELECTOR, "button.btn-choice")
            assert [b.text for b in buttons] == ["Retry", "Continue", "Abort"]
            # A gloved finger's targets on the tablet, side by side within its width.
            assert all(b.size["height"] >= 80 for b in buttons)
            assert max(b.rect["x"] + b.rect["width"] for b in buttons) <= 800
            assert header_overlaps(driver) == []
            save_screenshot(driver, shots / "operator-tablet.png", width=560)

            # Continue: a reason first (Next stays off without one), then a confirmation.
            continue_button = next(b for b in buttons if b.text == "Continue")
            continue_button.click()
            dialog = driver.find_element(By.ID, "answer-dialog")
            wait_for(driver, lambda d: dialog.is_displayed(), "the reason dialog")
            assert not running.done()  # nothing went to the robot yet
            next_button = driver.find_element(By.ID, "answer-next")
            assert not next_button.is_enabled()
            presets = driver.find_elements(By.CSS_SELECTOR, "#answer-presets .reason-preset")
            assert [p.text for p in presets] == PRESETS
            presets[0].click()
            reason = driver.find_element(By.ID, "answer-reason")
            assert reason.get_property("value") == PRESETS[0]
            assert presets[0].get_attribute("aria-pressed") == "true"
            reason.clear()
            reason.send_keys(TYPED)
            wait_for(driver, lambda d: next_button.is_enabled(), "Next enabled by a reason")
            save_screenshot(driver, shots / "operator-reason.png", width=560)
            next_button.click()
            summary = driver.find_element(By.ID, "answer-summary")
            wait_for(driver, lambda d: summary.is_displayed(), "the confirmation")
            assert "Continue" in summary.text
            assert "anna" in summary.text
            assert TYPED in summary.text
            assert not running.done()
            # Back keeps the reason; confirming sends it.
            driver.find_element(By.ID, "answer-back").click()
            wait_for(driver, lambda d: reason.is_displayed(), "back to the reason")
            assert reason.get_property("value") == TYPED
            next_button.click()
            confirm = driver.find_element(By.ID, "answer-confirm")
            wait_for(driver, lambda d: confirm.is_displayed(), "the confirmation again")
            confirm.click()

            outcome = running.result(WAIT_S)
            wait_for(driver, lambda d: not dialog.is_displayed(), "the dialog closed")
            wait_for(driver, lambda d: empty.is_displayed(), "the call gone from the page")
            wait_for(
                driver,
                lambda d: not d.find_elements(By.CSS_SELECTOR, "article.operator-call"),
                "the answered card removed",
            )
            status = driver.find_element(By.ID, "operator-status")
            assert "answered Continue as anna" in status.text
            recent = driver.find_element(By.ID, "operator-recent")
            wait_for(driver, lambda d: TYPED in recent.text, "the latest answers")
            assert "Continue by anna" in recent.text

            # The robot got the choice, the name and the reason.
            assert outcome.ok, outcome
            answer: dict[str, Any] = outcome.data["operator_answers"][0]
            assert (answer["choice"], answer["operator"], answer["reason"]) == (
                "continue",
                "anna",
                TYPED,
            )
            assert any(TYPED in n and "anna" in n for n in notes)
            assert "anna accepted" in outcome.message

            # The failed result's row carries the annotation; the filter finds it.
            person = Browserless(server.url)
            assert person.post_json("/api/login", {"user": "anna", "pin": ANNA_PIN}).status == 200
            rows = person.get("/api/results?operator=anna").json()["results"]
            assert len(rows) == 1
            assert (rows[0]["inspection"], rows[0]["passed"]) == ("magnet_check", False)
            assert rows[0]["operator"]["name"] == "anna"
            assert rows[0]["operator"]["choice"] == "continue"
            assert rows[0]["operator"]["reason"] == TYPED

            # A 1920x1080 wall screen: a second call, read from a few metres.
            viewport(driver, 1920, 1080)
            result = robot.inspect("magnet_check", overlay=True)
            overlay = next(i for i in result.images if i.role is ImageRole.OVERLAY)
            asked = pool.submit(
                robot.operator_call,
                "inspection 'magnet_check' failed 3 time(s): magnet missing",
                inspection="magnet_check",
                skill="quality_control",
                images=(overlay,),
                deadline_s=120.0,
                result_id=result.result_id,
            )
            card = wait_for(
                driver,
                lambda d: d.find_element(By.CSS_SELECTOR, 'article.operator-call[data-call="2"]'),
                "the second call",
            )
            assert len(driver.find_elements(By.CSS_SELECTOR, "article.operator-call")) == 1
            image = card.find_element(By.CSS_SELECTOR, "img.operator-image")
            wait_for(driver, lambda d: image.get_property("complete"), "the overlay image")
            buttons = card.find_elements(By.CSS_SELECTOR, "button.btn-choice")
            assert all(b.size["height"] >= 100 for b in buttons)
            assert all(b.is_enabled() for b in buttons)
            verdict = card.find_element(By.CSS_SELECTOR, ".operator-verdict")
            size = float(verdict.value_of_css_property("font-size").removesuffix("px"))
            assert size >= 36  # legible across the cell
            assert header_overlaps(driver) == []
            save_screenshot(driver, shots / "operator-wall.png", width=1152)
            buttons[0].click()  # Retry: no reason asked
            retried = asked.result(WAIT_S)
            assert (retried.choice, retried.operator, retried.reason) == ("retry", "anna", "")

            # The cell's laptop size keeps one row of header without overlap.
            viewport(driver, 1440, 900)
            assert header_overlaps(driver) == []

            # A badge reader: after Log out the badge field has the focus; the reader types
            # the badge's token and Enter.
            driver.find_element(By.ID, "logout").click()
            wait_for(
                driver,
                lambda d: d.switch_to.active_element.get_attribute("id") == "login-token",
                "the badge field focused",
            )
            driver.switch_to.active_element.send_keys(BEN_BADGE + "\n")
            wait_for(driver, lambda d: who.text == "ben", "ben signed in by his badge")
            assert console_errors(driver) == []
        finally:
            robot.close()
            viewport(driver, 1280, 800)
