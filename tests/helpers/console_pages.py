"""What the console's browser tests share: waiting for a condition, which page is shown, and
signing in. Import it after ``pytest.importorskip("selenium")`` (it imports selenium)."""

from __future__ import annotations

from collections.abc import Callable
from typing import TypeVar

from browser import console_errors
from console_server import TOKEN, RunningConsole
from selenium.common.exceptions import StaleElementReferenceException
from selenium.webdriver.common.by import By
from selenium.webdriver.remote.webdriver import WebDriver
from selenium.webdriver.support.ui import WebDriverWait

T = TypeVar("T")
WAIT_S = 60.0
"""Only bounds a hang: each wait ends as soon as its condition holds."""


def wait_for(
    driver: WebDriver, condition: Callable[[WebDriver], T], what: str, *, timeout_s: float = WAIT_S
) -> T:
    """Wait until ``condition`` is truthy; elements the page re-rendered meanwhile are looked
    up again on the next round (pages refresh themselves)."""
    wait = WebDriverWait(driver, timeout_s, ignored_exceptions=(StaleElementReferenceException,))
    return wait.until(condition, f"timed out waiting for {what}")


def visible_page(driver: WebDriver) -> str:
    """The ids of the console's pages shown now, comma-separated."""
    return str(
        driver.execute_script(
            "return [...document.querySelectorAll('section.page')]"
            ".filter((s) => !s.hidden).map((s) => s.id).join(',');"
        )
    )


def sign_in(driver: WebDriver, server: RunningConsole, page: str, token: str = TOKEN) -> None:
    """Open ``page`` as a new visitor: the login page first, then ``page`` once signed in."""
    driver.delete_all_cookies()
    driver.get(f"{server.url}#/{page}")
    console_errors(driver)
    wait_for(driver, lambda d: visible_page(d) == "page-login", "the login page")
    driver.find_element(By.ID, "login-token").send_keys(token)
    driver.find_element(By.ID, "login-submit").click()
    wait_for(driver, lambda d: visible_page(d) == f"page-{page}", f"the {page} page")


def answer_why(driver: WebDriver, why: str) -> None:
    """Answer the page's "why" dialog (js/why.js), opened by a save or a revert: type the
    reason and confirm."""
    dialog = wait_for(
        driver,
        lambda d: (e := d.find_element(By.ID, "why-dialog")).is_displayed() and e,
        "the why dialog",
    )
    assert driver.find_element(By.ID, "why-ok").get_property("disabled"), "confirmable unasked"
    driver.find_element(By.ID, "why-text").send_keys(why)
    driver.find_element(By.ID, "why-ok").click()
    wait_for(driver, lambda d: not dialog.is_displayed(), "the why dialog to close")
