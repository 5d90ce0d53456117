"""The ``caliper`` inspection: configuration errors that name file, line and key, values in mm
through a real server on loopback, and a part that is not there failing with a reason."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest
from loopback import client_for, run, server_in_thread

from protocol import schema
from simulation.flat_parts import bar, plane_point, render_flat_part
from simulation.scene import camera_preset
from vision_server.config import ConfigError
from vision_server.inspections import RESULT_KINDS
from vision_server.service import CellRuntime

CAMERA = """\
cameras:
  tool:
    source: request
    intrinsics: {width: 1024, height: 768, fx: 1400, fy: 1400, cx: 511.5, cy: 383.5,
                 distortion: [-0.08, 0.05, 0.0004, -0.0003, 0.0]}
  plain: {source: request}
"""

WIDTH = (
    """\
server: {port: 0}
results: {enabled: false}
"""
    + CAMERA
    + """\
inspections:
  - name: bar_width
    type: caliper
    camera: tool
    units: mm
    plane_distance_m: 0.35
    measurements:
      - {name: width, kind: width, band: {center: [700, 300], length: 80, width: 9,
         angle_rad: 0.3}, min: 9.9, max: 10.1}
      - {name: left, kind: edge, band: {center: [700, 300], length: 80, width: 9,
         angle_rad: 0.3}, polarity: dark_to_light, select: first}
"""
)


@pytest.fixture
def runtime(tmp_path: Path) -> Iterator[CellRuntime]:
    path = tmp_path / "cell.yaml"
    path.write_text(WIDTH, encoding="utf-8")
    cell = CellRuntime(path)
    try:
        yield cell
    finally:
        cell.close()


def _bar_image(width_mm: float) -> np.ndarray:
    camera, _, _ = camera_preset("dmk31bf03")
    centre = plane_point(camera, 350.0, (700.0, 300.0))
    part = bar(centre, width_mm, 0.3)
    return render_flat_part(camera, 350.0, part, (650, 250, 100, 100), seed=3)


def _inspect(runtime: CellRuntime, image: np.ndarray) -> tuple[bool, dict[str, object]]:
    async def body() -> tuple[bool, dict[str, object]]:
        with server_in_thread(runtime.catalog) as server:
            async with client_for(server) as client:
                result = await client.inspect("bar_width", image, overlay=True)
                assert result.images, "an overlay was asked for"
                return result.passed, dict(result.data)

    return run(body())


def test_a_width_in_millimetres_over_the_wire(runtime: CellRuntime) -> None:
    passed, data = _inspect(runtime, _bar_image(10.0))
    schema.validate_data("caliper", data)
    assert passed
    assert data["units"] == "mm"
    width, left = data["measurements"]  # type: ignore[misc]
    assert width["unit"] == "mm"
    assert width["value"] == pytest.approx(10.0, abs=0.02)
    assert left["value"] == pytest.approx(40 * 0.25 - 5.0, abs=0.1)  # from the band's start
    summary = RESULT_KINDS["caliper"].summary(data)
    assert summary["failed"] == 0.0
    assert summary["value_1"] == pytest.approx(10.0, abs=0.02)
    assert np.isnan(summary["value_8"])


def test_out_of_tolerance_and_absent_parts_fail_with_what_was_measured(
    runtime: CellRuntime,
) -> None:
    passed, data = _inspect(runtime, _bar_image(10.3))
    assert not passed
    assert data["failed"] == 1
    flat = np.full((768, 1024), 60, np.uint8)
    passed, data = _inspect(runtime, flat)
    schema.validate_data("caliper", data)
    assert not passed
    assert data.get("value") is None  # null: sent as absent
    width = data["measurements"][0]  # type: ignore[index]
    assert "no dark_to_light edge followed by a light_to_dark edge" in width["reason"]


def error(tmp_path: Path, inspection: str) -> str:
    path = tmp_path / "cell.yaml"
    path.write_text(CAMERA + "inspections:\n" + inspection, encoding="utf-8")
    with pytest.raises(ConfigError) as info:
        CellRuntime(path).close()
    return str(info.value)


BAND = "band: {center: [100, 100], length: 40}"


@pytest.mark.parametrize(
    ("entry", "wanted"),
    [
        (
            "{name: c, type: caliper, camera: plain, units: mm, plane_distance_m: 0.3, "
            f"measurements: [{{name: e, kind: edge, {BAND}}}]}}",
            "plane_distance_m: plane_distance_m needs the intrinsics of camera 'plain'",
        ),
        (
            f"{{name: c, type: caliper, camera: tool, units: mm, measurements: [{{name: e, "
            f"kind: edge, {BAND}}}]}}",
            "units: units: mm needs one calibration of the measuring plane",
        ),
        (
            f"{{name: c, type: caliper, camera: tool, mm_per_px: 0.1, measurements: [{{name: e, "
            f"kind: edge, {BAND}}}]}}",
            "mm_per_px: mm_per_px is for units: mm",
        ),
        (
            "{name: c, type: caliper, camera: tool, measurements: [{name: e, kind: edge, "
            "band: {center: [1010, 100], length: 40}}]}",
            "outside the camera's 1024x768 image",
        ),
        (
            f"{{name: c, type: caliper, camera: tool, measurements: [{{name: e, kind: edge, "
            f"{BAND}}}, {{name: d, kind: distance, from: e, to: l}}]}}",
            "to: 'l' is not a measurement above this one (above: e)",
        ),
        (
            f"{{name: c, type: caliper, camera: tool, measurements: [{{name: e, kind: edge, "
            f"{BAND}}}, {{name: d, kind: distance, from: e, to: e}}]}}",
            "to: 'e' is a edge; a distance is to a line",
        ),
        (
            f"{{name: c, type: caliper, camera: tool, measurements: [{{name: w, kind: width, "
            f"{BAND}, tolerance: 1}}]}}",
            "tolerance: tolerance is around expected",
        ),
        (
            f"{{name: c, type: caliper, camera: tool, measurements: [{{name: e, kind: edge, "
            f"{BAND}, radius: 3}}]}}",
            "radius: unknown key",
        ),
        (
            f"{{name: c, type: caliper, camera: tool, roi: [0, 0, 10, 10], measurements: "
            f"[{{name: e, kind: edge, {BAND}}}]}}",
            "roi: a caliper reads where its measurements' bands are",
        ),
        (
            "{name: c, type: caliper, camera: tool, measurements: [{name: e, kind: edge, "
            "band: {center: [100, 100], length: 2}}]}",
            "band length must be >= 3 px",
        ),
        (
            f"{{name: c, type: caliper, camera: tool, measurements: [{{name: e, kind: edge, "
            f"{BAND}, min: 3, max: 2}}]}}",
            "min: min (3) is above max (2)",
        ),
        ("{name: c, type: caliper, camera: tool}", "a caliper needs at least one measurement"),
    ],
)
def test_bad_measurements_name_file_line_and_key(tmp_path: Path, entry: str, wanted: str) -> None:
    message = error(tmp_path, f"  - {entry}\n")
    assert "cell.yaml:8" in message
    assert wanted in message


def test_a_band_outside_a_smaller_image_is_a_bad_image_that_names_it(tmp_path: Path) -> None:
    from protocol import BadImage
    from vision_server import InspectionInput

    path = tmp_path / "cell.yaml"
    path.write_text(
        CAMERA + "inspections:\n  - {name: c, type: caliper, camera: plain, measurements: "
        f"[{{name: e, kind: edge, {BAND}}}]}}\n",
        encoding="utf-8",
    )
    runtime = CellRuntime(path)
    try:
        inspection = runtime.catalog.inspections["c"]
        with pytest.raises(BadImage, match=r"band at \(100.0, 100.0\).*outside the 64x48 image"):
            inspection.run(InspectionInput(np.zeros((48, 64), np.uint8)), overlay=False)
    finally:
        runtime.close()
