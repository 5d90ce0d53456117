"""The Results page in real headless Chromium against the real server with the example cell
(tests/helpers/console_server.py): the filter (inspection, verdict, time, peer) narrows the
table to exactly the matching rows, a row opens its stored overlay (and its input on the
toggle), and the per-inspection statistics show count, pass rate and p50/p99 over the window.

Rows come from real tries through the console (overlays drawn by the inspection) and from
entries written into the server's own result log with chosen times, peers and durations, so
that every expected row and figure is known here.
"""

from __future__ import annotations

import time
from collections.abc import Iterator
from pathlib import Path

import cv2
import numpy as np
import pytest
from browser import console_errors, headless_chromium
from console_server import Browserless, RunningConsole, console_server

from vision_server.results import ResultEntry, ResultLog

selenium = pytest.importorskip("selenium")
from console_pages import sign_in, wait_for  # noqa: E402
from selenium.webdriver.common.by import By  # noqa: E402
from selenium.webdriver.remote.webdriver import WebDriver  # noqa: E402
from selenium.webdriver.support.ui import Select  # noqa: E402

pytestmark = pytest.mark.slow
RED = (255, 0, 0)  # RGB, as a canvas reads it: the failing ROI's rectangle on the overlay


@pytest.fixture(scope="module")
def driver() -> Iterator[WebDriver]:
    with headless_chromium() as d:
        yield d


@pytest.fixture
def server(tmp_path: Path) -> Iterator[RunningConsole]:
    with console_server(tmp_path) as running:
        yield running


def log_of(server: RunningConsole) -> ResultLog:
    log = server.app.service.results
    assert log is not None
    return log


def seed(
    server: RunningConsole,
    inspection: str,
    *,
    age_s: float,
    passed: bool,
    peer: str,
    duration_ms: float = 2.0,
    image: np.ndarray | None = None,
) -> int:
    """A row in the server's own log, ``age_s`` seconds old."""
    row_id = log_of(server).record(
        ResultEntry(
            time=time.time() - age_s,
            inspection=inspection,
            camera="qc",
            passed=passed,
            data={"seeded": True},
            duration_ms=duration_ms,
            config_hash="seeded",
            peer=peer,
            image=image,
        )
    )
    assert row_id is not None
    return row_id


def shown_ids(driver: WebDriver) -> set[int]:
    return {
        int(i)
        for i in driver.execute_script(
            "return [...document.querySelectorAll('#results-body tr')].map((r) => r.dataset.id);"
        )
    }


def wait_for_rows(driver: WebDriver, wanted: set[int], what: str) -> None:
    wait_for(driver, lambda d: shown_ids(d) == wanted, f"the rows {sorted(wanted)} ({what})")


def pixel(driver: WebDriver, u: int, v: int) -> tuple[int, int, int]:
    """The RGB of pixel (u, v) of the detail's image as loaded (drawn on a canvas)."""
    rgb = driver.execute_script(
        "const i = document.getElementById('rd-image');"
        "const c = document.createElement('canvas');"
        "c.width = i.naturalWidth; c.height = i.naturalHeight;"
        "const g = c.getContext('2d'); g.drawImage(i, 0, 0);"
        "return [...g.getImageData(arguments[0], arguments[1], 1, 1).data.slice(0, 3)];",
        u,
        v,
    )
    return int(rgb[0]), int(rgb[1]), int(rgb[2])


def image_shows(driver: WebDriver, fragment: str) -> bool:
    image = driver.find_element(By.ID, "rd-image")
    return (
        image.is_displayed()
        and fragment in (image.get_attribute("src") or "")
        and bool(image.get_property("complete"))
        and int(image.get_property("naturalWidth")) > 0
    )


def test_the_results_filter_narrows_to_the_matching_rows(
    driver: WebDriver, server: RunningConsole
) -> None:
    old = seed(server, "magnet_check", age_s=7200, passed=False, peer="10.0.0.7:41000")
    locate = seed(server, "cap_locate", age_s=120, passed=True, peer="10.0.0.8:41001")
    good = seed(server, "magnet_check", age_s=60, passed=True, peer="10.0.0.8:41001")
    bad = seed(server, "magnet_check", age_s=30, passed=False, peer="10.0.0.7:41002")
    client = Browserless(server.url)
    assert client.login().status == 200
    assert client.try_("magnet_check", {"source": "camera"}).json()["verdict"] == "fail"
    (tried,) = (r.id for r in log_of(server).query(limit=1))
    everything = {old, locate, good, bad, tried}

    sign_in(driver, server, "results")
    wait_for_rows(driver, everything, "no filter")
    wait_for(
        driver,
        lambda d: d.find_elements(By.CSS_SELECTOR, "#f-inspection option[value=magnet_check]"),
        "the inspection filter's choices",
    )
    Select(driver.find_element(By.ID, "f-inspection")).select_by_value("magnet_check")
    wait_for_rows(driver, {old, good, bad, tried}, "inspection")
    Select(driver.find_element(By.ID, "f-verdict")).select_by_value("fail")
    wait_for_rows(driver, {old, bad, tried}, "inspection and verdict")
    # Since one hour ago, typed as the browser's local time (datetime-local).
    since_ms = (time.time() - 3600) * 1000
    driver.execute_script(
        "const d = new Date(arguments[0]); const p = (n) => String(n).padStart(2, '0');"
        "document.getElementById('f-since').value = `${d.getFullYear()}-${p(d.getMonth() + 1)}-"
        "${p(d.getDate())}T${p(d.getHours())}:${p(d.getMinutes())}:${p(d.getSeconds())}`;",
        since_ms,
    )
    driver.find_element(By.ID, "f-apply").click()
    wait_for_rows(driver, {bad, tried}, "inspection, verdict and time")
    driver.find_element(By.ID, "f-peer").send_keys("10.0.0.7")
    driver.find_element(By.ID, "f-apply").click()
    wait_for_rows(driver, {bad}, "inspection, verdict, time and peer")
    rows = driver.execute_script(
        "return [...document.querySelectorAll('#results-body tr')].map((r) => r.innerText);"
    )
    assert "10.0.0.7:41002" in rows[0]
    assert "FAIL" in rows[0].upper()

    driver.find_element(By.ID, "f-clear").click()
    wait_for_rows(driver, everything, "cleared")
    driver.find_element(By.ID, "f-peer").send_keys("console ")
    driver.find_element(By.ID, "f-apply").click()
    wait_for_rows(driver, {tried}, "the console's own tries by peer")
    assert console_errors(driver) == []


def test_a_row_opens_its_stored_overlay_and_toggles_to_the_input(
    driver: WebDriver, server: RunningConsole
) -> None:
    client = Browserless(server.url)
    assert client.login().status == 200
    # The page's try asks for no overlay here: the log keeps one all the same.
    reply = client.try_("magnet_check", {"source": "camera", "overlay": False})
    assert reply.json()["verdict"] == "fail"
    (tried,) = (r.id for r in log_of(server).query(limit=1))
    raw = client.get(f"/api/results/{tried}/image.png")
    frame = cv2.imdecode(np.frombuffer(raw.body, np.uint8), cv2.IMREAD_COLOR)
    bare = seed(server, "magnet_check", age_s=5, passed=False, peer="old:1", image=frame)

    sign_in(driver, server, "results")
    wait_for(driver, lambda d: tried in shown_ids(d), "the try's row")
    driver.find_element(By.CSS_SELECTOR, f"#results-body tr[data-id='{tried}']").click()
    wait_for(driver, lambda d: image_shows(d, f"/{tried}/image.png?overlay=1"), "the overlay")
    # The failing ROI [486, 236, 50, 60] is outlined in red on the overlay, not on the input.
    assert pixel(driver, 500, 236) == RED
    values = driver.find_element(By.ID, "rd-values").text
    assert "dark_fraction" in values
    assert "value" in values
    timing = driver.find_element(By.ID, "rd-timing").text
    assert "inspect" in timing
    assert "ms" in timing
    assert "FAIL" in driver.find_element(By.ID, "rd-verdict").text
    driver.find_element(By.CSS_SELECTOR, "label:has(#rd-view-input)").click()
    wait_for(driver, lambda d: image_shows(d, f"/{tried}/image.png?overlay=0"), "the input")
    assert pixel(driver, 500, 236) != RED

    # A row without an overlay opens on its input and says why.
    wait_for(driver, lambda d: bare in shown_ids(d), "the row without an overlay")
    driver.find_element(By.CSS_SELECTOR, f"#results-body tr[data-id='{bare}']").click()
    wait_for(driver, lambda d: image_shows(d, f"/{bare}/image.png?overlay=0"), "its input")
    assert driver.find_element(By.ID, "rd-nooverlay").is_displayed()
    assert not driver.find_element(By.ID, "rd-noimage").is_displayed()
    assert console_errors(driver) == []


def test_the_statistics_show_count_pass_rate_and_timing_over_the_window(
    driver: WebDriver, server: RunningConsole
) -> None:
    # station_qr: ten results in the last hour, 7 passed, 1..10 ms (p50 5.5, p99 9.91), and
    # one more two hours ago, inside an 8-hour window only.
    for n in range(10):
        seed(server, "station_qr", age_s=60 + n, passed=n < 7, peer="r:1", duration_ms=n + 1.0)
    seed(server, "station_qr", age_s=7200, passed=False, peer="r:1", duration_ms=50.0)
    # magnet_check: one result ("1 result", not "1 results"), and a console try that no
    # statistic counts (docs/console.md, "Tries in the result log").
    seed(server, "magnet_check", age_s=30, passed=True, peer="r:1")
    tried = seed(server, "magnet_check", age_s=20, passed=True, peer="console 127.0.0.1:1")

    sign_in(driver, server, "results")
    Select(driver.find_element(By.ID, "stats-window")).select_by_value("3600")

    def card_text(d: WebDriver) -> str:
        cards = d.find_elements(By.CSS_SELECTOR, ".stat-card[data-inspection=station_qr]")
        return cards[0].text if cards else ""

    text = wait_for(driver, lambda d: "10 results" in (t := card_text(d)) and t, "1 hour stats")
    assert "70 %" in text
    assert "p50 5.5 ms" in text
    assert "p99 9.91 ms" in text
    bars = driver.find_elements(By.CSS_SELECTOR, ".stat-card[data-inspection=station_qr] svg")
    assert len(bars) == 2  # pass rate per period, p50/p99 per period
    one = driver.find_element(By.CSS_SELECTOR, ".stat-card[data-inspection=magnet_check]").text
    assert "1 result\n" in one + "\n", one
    assert "1 results" not in one, one

    # The try's row says it is one; the production row beside it does not.
    def chips(d: WebDriver) -> list[int]:
        return list(
            d.execute_script(
                "return [...document.querySelectorAll('#results-body tr')]"
                ".filter((r) => r.querySelector('.try-chip')).map((r) => Number(r.dataset.id));"
            )
        )

    wait_for(driver, lambda d: chips(d) == [tried], "the try's chip")
    Select(driver.find_element(By.ID, "stats-window")).select_by_value("28800")
    text = wait_for(driver, lambda d: "11 results" in (t := card_text(d)) and t, "8 hour stats")
    assert "63.6 %" in text  # 7 of 11
    # An inspection without results in the window shows dashes, not NaN.
    empty = driver.find_element(By.CSS_SELECTOR, ".stat-card[data-inspection=cap_locate]").text
    assert "0 results" in empty
    assert "p50 —" in empty
    assert "NaN" not in empty
    assert console_errors(driver) == []
