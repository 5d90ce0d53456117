"""Every console page on the cell's 1280x800 touch screen, in real headless Chromium against
the real server with the example cell: nothing wider than the screen (no sideways scrolling)
and the navigation tabs and page buttons big enough for a finger."""

from __future__ import annotations

from collections.abc import Iterator

import pytest
from browser import headless_chromium
from console_server import console_server

selenium = pytest.importorskip("selenium")
from console_pages import sign_in, visible_page, wait_for  # noqa: E402
from selenium.webdriver.remote.webdriver import WebDriver  # noqa: E402

pytestmark = pytest.mark.slow
PAGES = ("cameras", "inspections", "results", "server", "operator")
MIN_TARGET_PX = 32
"""The smallest side of a button a finger can hit reliably (Apple and Android ask 44 and 48
CSS px for primary targets; 32 is the floor for secondary ones)."""


@pytest.fixture(scope="module")
def driver() -> Iterator[WebDriver]:
    with headless_chromium() as d:
        yield d


def test_every_page_fits_the_touch_screen(
    driver: WebDriver, tmp_path_factory: pytest.TempPathFactory
) -> None:
    with console_server(tmp_path_factory.mktemp("touch")) as server:
        sign_in(driver, server, PAGES[0])
        for page in PAGES:
            driver.get(f"{server.url}#/{page}")
            wait_for(driver, lambda d, p=page: visible_page(d) == f"page-{p}", f"the {page} page")
            overflow = driver.execute_script(
                "return document.documentElement.scrollWidth - window.innerWidth;"
            )
            assert overflow <= 0, f"the {page} page is {overflow} px wider than the screen"
            small = driver.execute_script(
                """
                const min = arguments[0];
                const targets = 'nav button, nav a, section.page:not([hidden]) button';
                return [...document.querySelectorAll(targets)]
                  .filter((b) => b.offsetParent !== null)
                  .map((b) => [b.textContent.trim() || b.id, b.getBoundingClientRect()])
                  .filter(([, r]) => r.width < min || r.height < min)
                  .map(([name, r]) => `${name} ${Math.round(r.width)}x${Math.round(r.height)}`);
                """,
                MIN_TARGET_PX,
            )
            assert not small, f"buttons too small for a finger on the {page} page: {small}"
