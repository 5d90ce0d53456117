"""The impact preview in real headless Chromium against the real server (docs/console.md,
"Impact before save"): an integrator changes ``magnet_check``'s threshold on the Inspections
page, presses Preview impact, and the flipped results the page shows are exactly those that
``vision-server replay`` predicts for the same change on the same log (and those the images'
design predicts, tests/helpers/impact_log.py). A flip opens its stored result.

With ``CONSOLE_SCREENSHOTS=docs/console`` the panel's screenshot replaces docs/console/impact.png.
"""

from __future__ import annotations

import contextlib
import io
import json
import os
from collections.abc import Iterator
from pathlib import Path

import pytest
from browser import console_errors, headless_chromium, save_screenshot
from impact_log import BASE_MIN, BASE_THRESHOLD, changed_config, expected_pass, fill_log
from impact_log import impact_server as running_impact_server

from vision_server.commands import main

selenium = pytest.importorskip("selenium")
from console_pages import sign_in, wait_for  # noqa: E402
from selenium.webdriver.common.by import By  # noqa: E402
from selenium.webdriver.remote.webdriver import WebDriver  # noqa: E402

pytestmark = pytest.mark.slow
Flip = tuple[int, str, str]


@pytest.fixture(scope="module")
def driver() -> Iterator[WebDriver]:
    with headless_chromium() as d:
        yield d


def set_number(driver: WebDriver, selector: str, value: float) -> None:
    """Type ``value`` into a number field as a person would (select all, type)."""
    field = driver.find_element(By.CSS_SELECTOR, selector)
    driver.execute_script("arguments[0].select();", field)
    field.send_keys(str(value))


def shown_flips(driver: WebDriver) -> set[Flip]:
    """(result id, stored, new) of every flip the panel shows, from its two groups."""
    out: set[Flip] = set()
    for group, (stored, new) in (
        ("impact-pass-to-fail", ("pass", "fail")),
        ("impact-fail-to-pass", ("fail", "pass")),
    ):
        for item in driver.find_elements(By.CSS_SELECTOR, f"#{group} .impact-flip"):
            assert item.get_attribute("data-stored") == stored
            assert item.get_attribute("data-new") == new
            out.add((int(item.get_attribute("data-result-id") or 0), stored, new))
    return out


def preview(driver: WebDriver, last: int) -> str:
    """Press Preview impact for the newest ``last`` images; the status line when it is done."""
    old = driver.find_element(By.ID, "impact-status").text
    set_number(driver, "#impact-last", last)
    driver.find_element(By.ID, "impact-run").click()

    def done(d: WebDriver) -> str | None:
        status = d.find_element(By.ID, "impact-status").text
        running = d.find_element(By.ID, "impact-run").get_attribute("disabled")
        result = d.find_element(By.ID, "impact-result")
        return status if status != old and not running and result.is_displayed() else None

    return str(wait_for(driver, done, "the impact preview's answer"))


def cli_flips(config: Path, last: int) -> set[Flip]:
    out = io.StringIO()
    with contextlib.redirect_stdout(out):
        code = main(
            ["replay", "magnet_check", "--config", str(config), "--last", str(last), "--json"]
        )
    assert code in (0, 1), out.getvalue()
    answer = json.loads(out.getvalue())
    return {(f["result_id"], f["stored"], f["new"]) for f in answer["flipped"]}


def test_a_threshold_change_flips_on_the_page_what_the_replay_predicts(
    driver: WebDriver, tmp_path: Path
) -> None:
    shots = os.environ.get("CONSOLE_SCREENSHOTS")
    with running_impact_server(tmp_path) as server:
        rows = fill_log(server)
        sign_in(driver, server, "inspections")
        wait_for(
            driver,
            lambda d: d.find_elements(By.CSS_SELECTOR, ".list-item[data-inspection=magnet_check]"),
            "the inspection list",
        )
        driver.find_element(By.CSS_SELECTOR, ".list-item[data-inspection=magnet_check]").click()
        wait_for(
            driver,
            lambda d: d.find_elements(By.CSS_SELECTOR, "input.param-number[data-param=threshold]"),
            "the threshold's field",
        )

        # The threshold from 90 to 120: the mid-grey magnets now count as dark.
        set_number(driver, "input.param-number[data-param=threshold]", 120)
        wait_for(
            driver,
            lambda d: "threshold: 120" in d.find_element(By.ID, "yaml-snippet").text,
            "the pending change",
        )
        status = preview(driver, 500)
        shown = shown_flips(driver)
        predicted = cli_flips(changed_config(server, tmp_path, 120, BASE_MIN), 500)
        design = {
            (row.result_id, "fail", "pass")
            for row in rows
            if not expected_pass(row.design, BASE_THRESHOLD, BASE_MIN)
            and expected_pass(row.design, 120, BASE_MIN)
        }
        assert shown == predicted == design, (shown, predicted, design)
        assert f"{len(design)} verdicts flip of {len(rows)} replayed" in status
        counts = {
            e.get_attribute("data-count"): e.find_element(
                By.CSS_SELECTOR, ".impact-count-value"
            ).text
            for e in driver.find_elements(By.CSS_SELECTOR, "#impact-counts .impact-count")
        }
        assert counts["fail_to_pass"] == str(len(design))
        assert counts["pass_to_fail"] == "0"
        assert counts["with_image"] == str(len(rows))
        # Rows stored under the earlier file are marked as such.
        older = driver.find_elements(By.CSS_SELECTOR, ".impact-flip[data-current-config=false]")
        assert older
        assert all(o.find_elements(By.CSS_SELECTOR, ".impact-older") for o in older)

        # And the minimum too: the thin dark magnets fail now, both groups fill.
        set_number(driver, "input.param-number[data-param=min]", 0.45)
        wait_for(
            driver,
            lambda d: "min: 0.45" in d.find_element(By.ID, "yaml-snippet").text,
            "the pending change of min",
        )
        preview(driver, 500)
        shown = shown_flips(driver)
        predicted = cli_flips(changed_config(server, tmp_path, 120, 0.45), 500)
        assert shown == predicted
        assert {(s, n) for _, s, n in shown} == {("pass", "fail"), ("fail", "pass")}

        # A flip opens its stored result beside the overlay with the change.
        first = driver.find_element(By.CSS_SELECTOR, "#impact-pass-to-fail .impact-flip")
        result_id = first.get_attribute("data-result-id")
        first.click()
        wait_for(
            driver,
            lambda d: d.execute_script(
                "const i = document.getElementById('impact-viewer-stored');"
                "return i.complete && i.naturalWidth > 0 && i.src.includes(arguments[0]);",
                f"/api/results/{result_id}/",
            ),
            "the stored result's image",
        )
        title = driver.find_element(By.ID, "impact-viewer-title").text
        assert f"#{result_id}" in title
        assert "stored PASS" in title
        assert "FAIL" in title
        # The editor may give the whole edited mapping instead of options: sent as config.
        bodies = driver.execute_async_script(
            "const done = arguments[0];"
            "import('/static/js/impact.js').then((m) => done(["
            "  m.impactBody({name: 'magnet_check', config: {name: 'magnet_check', min: 0.3}}, 7),"
            "  m.impactBody({name: 'magnet_check', options: {threshold: 120}}, 8)]));"
        )
        assert bodies == [
            {"config": {"name": "magnet_check", "min": 0.3}, "last": 7},
            {"options": {"threshold": 120}, "last": 8},
        ]
        if shots:
            driver.execute_script(
                "document.getElementById('impact-panel').scrollIntoView({block: 'start'});"
            )
            save_screenshot(driver, Path(shots) / "impact.png")
        assert console_errors(driver) == []


def test_few_stored_images_are_said_on_the_page(driver: WebDriver, tmp_path: Path) -> None:
    """The default store_images (failures): the page says why few results can be replayed."""
    from console_server import console_server

    with console_server(tmp_path) as server:
        sign_in(driver, server, "inspections")
        wait_for(
            driver,
            lambda d: d.find_elements(By.CSS_SELECTOR, ".list-item[data-inspection=magnet_check]"),
            "the inspection list",
        )
        driver.find_element(By.CSS_SELECTOR, ".list-item[data-inspection=magnet_check]").click()
        preview(driver, 20)
        note = driver.find_element(By.ID, "impact-note")
        assert note.is_displayed()
        assert "store_images: failures" in note.text
        assert "None of the results looked at has a stored image" in note.text
        assert console_errors(driver) == []


def test_an_operator_is_not_offered_the_preview(driver: WebDriver, tmp_path: Path) -> None:
    """The preview runs inspections with other parameters: the integrator's (403 for an
    operator), so the operator's page does not show it."""
    from console_server import console_server

    operator = "operator-token-0123456789"
    with console_server(tmp_path, operator_token=operator) as server:
        sign_in(driver, server, "inspections", token=operator)
        wait_for(
            driver,
            lambda d: d.find_elements(By.CSS_SELECTOR, ".list-item[data-inspection=magnet_check]"),
            "the inspection list",
        )
        driver.find_element(By.CSS_SELECTOR, ".list-item[data-inspection=magnet_check]").click()
        wait_for(
            driver,
            lambda d: d.execute_script("return document.body.dataset.role") == "operator",
            "the operator's role on the page",
        )
        assert not driver.find_element(By.ID, "impact-panel").is_displayed()
        assert console_errors(driver) == []
