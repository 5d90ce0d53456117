"""docs/console.md's walkthrough stays true: every step of tuning ``magnet_check`` from the
console alone, in real headless Chromium against the real server with the example cell
(tests/helpers/console_walkthrough.py). scripts/console_screenshots.py runs the same steps to
take the doc's screenshots."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import pytest
from browser import headless_chromium
from console_server import console_server

selenium = pytest.importorskip("selenium")
from console_walkthrough import walk  # noqa: E402
from selenium.webdriver.remote.webdriver import WebDriver  # noqa: E402

pytestmark = pytest.mark.slow


@pytest.fixture(scope="module")
def driver() -> Iterator[WebDriver]:
    with headless_chromium() as d:
        yield d


def test_the_magnet_check_walkthrough_of_the_docs(driver: WebDriver, tmp_path: Path) -> None:
    shots = tmp_path / "shots"
    (tmp_path / "cell").mkdir()
    with console_server(tmp_path / "cell") as server:
        walk(driver, server, shots)
    assert {p.name for p in shots.glob("*.png")} >= {
        "login.png",
        "cameras.png",
        "inspections.png",
        "results.png",
        "server.png",
    }
