"""Training an anomaly inspection from the console in real headless Chromium against the real
server (docs/console.md, "Training an anomaly inspection"): the integrator opens
``surface_check`` (untrained: every robot INSPECT so far ended in an error, its image kept),
picks the stored results of good parts in the Train panel, leaves out the scratched one, and
trains; the report shows the threshold and the file written, the model in force follows, and
the inspection then answers a robot with that model (``model_version`` 1) under the new
configuration hash. Passing results are checked by default once there are some.

With ``CONSOLE_SCREENSHOTS=docs/console`` the panel's screenshot replaces docs/console/train.png.
"""

from __future__ import annotations

import os
from collections.abc import Iterator
from pathlib import Path

import pytest
from browser import console_errors, headless_chromium, save_screenshot
from console_users import ANNA_PIN, CARLA_PIN
from train_cell import inspect, part_image, send_parts, train_server

from protocol import CellvisionError

selenium = pytest.importorskip("selenium")
from console_pages import visible_page, wait_for  # noqa: E402
from selenium.webdriver.common.by import By  # noqa: E402
from selenium.webdriver.remote.webdriver import WebDriver  # noqa: E402

pytestmark = pytest.mark.slow


@pytest.fixture(scope="module")
def driver() -> Iterator[WebDriver]:
    with headless_chromium() as d:
        yield d


def sign_in_as_carla(driver: WebDriver, url: str) -> None:
    driver.delete_all_cookies()
    driver.get(f"{url}#/inspections")
    console_errors(driver)
    wait_for(driver, lambda d: visible_page(d) == "page-login", "the login page")
    driver.find_element(By.ID, "login-user").send_keys("Carla")
    driver.find_element(By.ID, "login-pin").send_keys(CARLA_PIN)
    driver.find_element(By.ID, "login-submit").click()
    wait_for(driver, lambda d: visible_page(d) == "page-inspections", "the inspections page")


def open_inspection(driver: WebDriver, name: str) -> None:
    item = wait_for(
        driver,
        lambda d: d.find_elements(By.CSS_SELECTOR, f".list-item[data-inspection={name}]"),
        f"{name} in the list",
    )
    item[0].click()


def listed(driver: WebDriver) -> dict[int, tuple[str, bool]]:
    """result id → (verdict, checked) of every stored result the Train panel lists."""
    out = {}
    for item in driver.find_elements(By.CSS_SELECTOR, "#train-list .train-item"):
        box = item.find_element(By.CSS_SELECTOR, ".train-pick")
        out[int(item.get_attribute("data-result-id") or 0)] = (
            str(item.get_attribute("data-verdict")),
            bool(box.is_selected()),
        )
    return out


def text(driver: WebDriver, element_id: str) -> str:
    return str(driver.find_element(By.ID, element_id).text)


def test_pick_good_results_train_and_the_inspection_answers_with_the_model(
    driver: WebDriver, tmp_path: Path
) -> None:
    shots = os.environ.get("CONSOLE_SCREENSHOTS")
    with train_server(tmp_path) as server:
        good = send_parts(server, 10)
        inspect(server, "surface_check", part_image(50, scratch=True))
        scratched = server.app.service.results.query(inspection="surface_check", limit=1)[0].id
        old_hash = server.app.service.catalog.config_hash

        sign_in_as_carla(driver, server.url)
        # A presence check has no Train panel.
        open_inspection(driver, "magnet_check")
        wait_for(driver, lambda d: text(d, "insp-name") == "magnet_check", "magnet_check")
        assert not driver.find_element(By.ID, "train-panel").is_displayed()

        open_inspection(driver, "surface_check")
        wait_for(
            driver,
            lambda d: len(d.find_elements(By.CSS_SELECTOR, "#train-list .train-item")) == 11,
            "the stored results in the Train panel",
        )
        assert driver.find_element(By.ID, "train-panel").is_displayed()
        assert driver.find_element(By.ID, "train-model-none").is_displayed()
        shown = listed(driver)
        assert set(shown) == {*good, scratched}
        # Untrained, every run was an error: nothing passes, so nothing is checked.
        assert all(v == ("error", False) for v in shown.values()), shown
        assert "No passing result" in text(driver, "train-list-note")
        # The camera of surface_check is the robot's: its frames cannot be grabbed here.
        assert not driver.find_element(By.ID, "train-source-camera").is_enabled()

        driver.find_element(By.ID, "train-select-all").click()
        driver.find_element(
            By.CSS_SELECTOR, f".train-item[data-result-id='{scratched}'] .train-pick"
        ).click()
        assert text(driver, "train-selected-count") == "10 selected"
        driver.find_element(By.ID, "train-run").click()
        wait_for(
            driver,
            lambda d: text(d, "train-status").startswith("Trained") or text(d, "train-error"),
            "the training's report",
            timeout_s=120,
        )
        assert text(driver, "train-error") == ""
        assert text(driver, "train-report-images") == "10"
        assert text(driver, "train-report-model") == "models/surface_check.v1.npz"
        assert text(driver, "train-report-version") == "1"
        assert text(driver, "train-report-method") == "variation"
        assert float(text(driver, "train-report-threshold")) > 0
        assert text(driver, "train-report-false-reject") == "1.0 %"
        assert "%" in text(driver, "train-report-held-out")
        assert "Trained surface_check on 10 images" in text(driver, "train-status")
        new_hash = str(driver.find_element(By.ID, "train-report").get_attribute("data-config-hash"))
        assert new_hash != old_hash
        assert new_hash == server.app.service.catalog.config_hash
        # The model in force follows, and the configuration shown names the file.
        wait_for(
            driver,
            lambda d: d.find_element(By.ID, "train-model-facts").is_displayed(),
            "the model in force",
        )
        assert text(driver, "train-model-file") == "models/surface_check.v1.npz"
        assert text(driver, "train-model-version") == "1"
        assert text(driver, "train-model-images") == "10"
        assert text(driver, "train-model-threshold") == text(driver, "train-report-threshold")
        wait_for(
            driver,
            lambda d: "models/surface_check.v1.npz" in text(d, "insp-config"),
            "model: in the configuration shown",
        )
        if shots:
            driver.execute_script(
                "document.getElementById('train-panel').scrollIntoView({block: 'start'});"
            )
            save_screenshot(driver, Path(shots) / "train.png")

        # The inspection answers a robot with the new model, under the new hash.
        result = inspect(server, "surface_check", part_image(200))
        assert not isinstance(result, CellvisionError), result
        assert result.passed  # type: ignore[attr-defined]
        assert result.data["model_version"] == 1  # type: ignore[attr-defined]
        assert result.config_hash == new_hash  # type: ignore[attr-defined]
        bad = inspect(server, "surface_check", part_image(201, scratch=True))
        assert not isinstance(bad, CellvisionError), bad
        assert not bad.passed  # type: ignore[attr-defined]

        # Back on the inspection: its passing results are checked by default, the rest not.
        open_inspection(driver, "magnet_check")
        wait_for(driver, lambda d: not d.find_element(By.ID, "train-panel").is_displayed(), "hide")
        open_inspection(driver, "surface_check")
        wait_for(
            driver,
            lambda d: len(d.find_elements(By.CSS_SELECTOR, "#train-list .train-item")) == 13,
            "the stored results again",
        )
        shown = listed(driver)
        assert {i for i, (v, c) in shown.items() if c} == {
            i for i, (v, _) in shown.items() if v == "pass"
        }
        assert sorted(v for v, _ in shown.values()).count("pass") == 1
        driver.find_element(By.ID, "train-select-none").click()
        assert text(driver, "train-selected-count") == "0 selected"
        driver.find_element(By.ID, "train-select-passing").click()
        assert text(driver, "train-selected-count") == "1 selected"
        assert console_errors(driver) == []


def test_grab_frames_from_the_camera_and_train(driver: WebDriver, tmp_path: Path) -> None:
    """qc_surface's camera is the simulated QC camera: the panel grabs 8 frames from it and
    trains; an operator then sees the model in force and no training controls."""
    with train_server(tmp_path) as server:
        sign_in_as_carla(driver, server.url)
        open_inspection(driver, "qc_surface")
        wait_for(
            driver,
            lambda d: (
                d.find_element(By.ID, "train-panel").is_displayed()
                # textContent: the heading is shown in capitals (CSS)
                and d.find_element(By.ID, "train-title").get_attribute("textContent")
                == "Train qc_surface"
            ),
            "the Train panel of qc_surface",
        )
        camera = driver.find_element(By.ID, "train-source-camera")
        assert camera.is_enabled()
        camera.click()
        assert driver.find_element(By.ID, "train-frames").is_displayed()
        assert not driver.find_element(By.ID, "train-list").is_displayed()
        for field, value in (("train-frames", "8"), ("train-interval", "50")):
            box = driver.find_element(By.ID, field)
            driver.execute_script("arguments[0].select();", box)
            box.send_keys(value)
        driver.find_element(By.ID, "train-run").click()
        wait_for(
            driver,
            lambda d: text(d, "train-status").startswith("Trained") or text(d, "train-error"),
            "the training's report",
            timeout_s=120,
        )
        assert text(driver, "train-error") == ""
        assert text(driver, "train-report-images") == "8"
        assert text(driver, "train-report-model") == "models/qc_surface.v1.npz"
        assert text(driver, "train-model-version") == "1"
        assert (tmp_path / "models" / "qc_surface.v1.npz").is_file()

        # The operator views the model in force; training is the integrator's.
        driver.delete_all_cookies()
        driver.get(f"{server.url}#/inspections")
        wait_for(driver, lambda d: visible_page(d) == "page-login", "the login page")
        driver.find_element(By.ID, "login-user").send_keys("anna")
        driver.find_element(By.ID, "login-pin").send_keys(ANNA_PIN)
        driver.find_element(By.ID, "login-submit").click()
        wait_for(driver, lambda d: visible_page(d) == "page-inspections", "the inspections page")
        open_inspection(driver, "qc_surface")
        wait_for(
            driver,
            lambda d: d.find_element(By.ID, "train-model-facts").is_displayed(),
            "the model in force for the operator",
        )
        assert text(driver, "train-model-file") == "models/qc_surface.v1.npz"
        assert not driver.find_element(By.ID, "train-work").is_displayed()
        assert not driver.find_element(By.ID, "train-run").is_displayed()
        assert console_errors(driver) == []
