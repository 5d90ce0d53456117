"""The online view's graphics (vision_server/inspections/graphics.py): every inspection type's
real result, run on the golden images of test_inspections/, turned into shapes in image pixels
that lie where the result says it found things."""

from __future__ import annotations

import math
from functools import cache
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from vision_server.commands.golden import Case, load_case, run_images
from vision_server.inspections import MAX_SHAPES, result_shapes
from vision_server.inspections.job.frame import PartFrame, outline, roi_transform

CASES = Path(__file__).resolve().parents[2] / "test_inspections"


@cache
def _case(name: str) -> Case:
    return load_case(CASES / name)


def _run(name: str, image: str) -> tuple[Case, bool, dict[str, Any]]:
    case = _case(name)
    (got,) = run_images(case, [image])
    assert got.verdict in ("pass", "fail"), got
    return case, got.verdict == "pass", got.data


def _kinds(
    shapes: list[dict[str, Any]], kind: str, role: str | None = None
) -> list[dict[str, Any]]:
    return [s for s in shapes if s["kind"] == kind and (role is None or s["role"] == role)]


def _near(a: tuple[float, float], b: tuple[float, float], tol: float = 0.05) -> bool:
    return math.dist(a, b) <= tol


def test_presence_draws_its_roi_in_its_verdict_and_its_value() -> None:
    for image, verdict in (("in_slot.png", "pass"), ("empty.png", "fail")):
        case, passed, data = _run("example_cell_magnet_check", image)
        shapes = result_shapes(case.inspection, data, passed)
        (rect,) = _kinds(shapes, "rect")
        assert rect["role"] == verdict
        x, y, w, h = case.inspection.common.roi  # type: ignore[attr-defined]
        assert (rect["x"], rect["y"], rect["w"], rect["h"]) == (x, y, w, h)
        (text,) = _kinds(shapes, "text")
        assert text["text"] == f"dark_fraction = {data['value']:.3f}"


def test_a_circle_locate_draws_each_circle_with_its_radius_and_centre() -> None:
    case, passed, data = _run("cap_locate_circle", "two_caps.png")
    assert passed
    assert data["count"] == 2
    shapes = result_shapes(case.inspection, data, passed)
    circles = _kinds(shapes, "circle", "feature")
    points = _kinds(shapes, "point", "feature")
    assert len(circles) == len(points) == 2
    for feature, circle, point in zip(data["features"], circles, points, strict=True):
        assert _near((circle["u"], circle["v"]), (feature["u"], feature["v"]))
        assert circle["r"] == pytest.approx(feature["radius"], abs=0.01)
        assert _near((point["u"], point["v"]), (feature["u"], feature["v"]))
    assert [t["text"] for t in _kinds(shapes, "text")] == ["1", "2"]


@pytest.mark.parametrize("case_name", ["magnet_locate_template", "part_locate_template_scaled"])
def test_a_template_locate_draws_the_template_turned_and_scaled_at_its_pose(case_name: str) -> None:
    image = "rotated.png" if case_name == "magnet_locate_template" else "nearer.png"
    case, passed, data = _run(case_name, image)
    assert passed
    feature = data["features"][0]
    shapes = result_shapes(case.inspection, data, passed)
    (box,) = _kinds(shapes, "polygon", "feature")
    corners = np.array(box["points"])
    template = case.inspection.options["template"]  # type: ignore[attr-defined]
    scale = feature.get("scale") or 1.0
    h, w = template.shape[0] * scale, template.shape[1] * scale
    # its centre is the feature, its sides the template's size, its first side along the angle
    assert _near(tuple(corners.mean(axis=0)), (feature["u"], feature["v"]), 0.02)
    assert np.linalg.norm(corners[1] - corners[0]) == pytest.approx(w, abs=0.02)
    assert np.linalg.norm(corners[2] - corners[1]) == pytest.approx(h, abs=0.02)
    side = corners[1] - corners[0]
    assert math.atan2(side[1], side[0]) == pytest.approx(feature["angle"], abs=1e-3)


def test_a_blob_locate_draws_a_circle_of_the_blobs_area() -> None:
    case, passed, data = _run("magnet_locate_blob", "in_slot.png")
    feature = data["features"][0]
    shapes = result_shapes(case.inspection, data, passed)
    circle = _kinds(shapes, "circle", "feature")[0]
    assert math.pi * circle["r"] ** 2 == pytest.approx(feature["area"], rel=1e-3)


@pytest.mark.parametrize(
    ("case_name", "image"), [("station_qr", "near_0.6m.png"), ("label_codes", "datamatrix.png")]
)
def test_a_code_draws_its_corners_and_its_text(case_name: str, image: str) -> None:
    case, passed, data = _run(case_name, image)
    assert passed
    shapes = result_shapes(case.inspection, data, passed)
    polygon = _kinds(shapes, "polygon", "pass")[0]
    assert np.allclose(polygon["points"], data["corners"], atol=0.01)
    texts = [t["text"] for t in _kinds(shapes, "text")]
    shown = data.get("text_hri") or data["text"]  # a code's human-readable form
    assert any(shown[:20] in t for t in texts), texts


def test_a_code_that_is_not_found_draws_its_roi_only() -> None:
    case, passed, data = _run("station_qr", "nothing.png")
    assert not passed
    shapes = result_shapes(case.inspection, data, passed)
    assert not _kinds(shapes, "polygon")


def test_a_qr_pose_draws_the_code_and_its_axes_projected_at_the_codes_centre() -> None:
    case, passed, data = _run("station_pose", "frontal_0.8m.png")
    assert passed
    shapes = result_shapes(case.inspection, data, passed)
    assert np.allclose(_kinds(shapes, "polygon")[0]["points"], data["corners"], atol=0.01)
    (axes,) = _kinds(shapes, "axes", "frame")
    centre = np.mean(data["corners"], axis=0)
    # the code's origin is its centre (frontal: the axes start amid its corners)
    assert _near((axes["u"], axes["v"]), (centre[0], centre[1]), 2.0)
    for tip in ("x", "y", "z"):
        assert len(axes[tip]) == 2
    # x and y lie in the code's plane (frontal): each axis of side length spans a side
    side = math.dist(data["corners"][0], data["corners"][1])
    assert math.dist((axes["u"], axes["v"]), axes["x"]) == pytest.approx(side, rel=0.05)


def test_a_calibration_board_draws_every_corner_found() -> None:
    case, passed, data = _run("commissioning_board", "frontal.png")
    assert passed
    shapes = result_shapes(case.inspection, data, passed)
    points = _kinds(shapes, "point", "feature")
    assert len(points) == min(data["count"], MAX_SHAPES - 2)
    assert np.allclose([[p["u"], p["v"]] for p in points[:5]], data["corners"][:5], atol=0.01)


def test_a_caliper_draws_its_bands_edges_and_fits_in_their_verdicts() -> None:
    for image in ("nominal.png", "wide.png", "small_hole.png"):
        case, passed, data = _run("caliper_bracket", image)
        shapes = result_shapes(case.inspection, data, passed)
        specs = case.inspection.specs  # type: ignore[attr-defined]
        bands = _kinds(shapes, "polygon", "search")
        rings = _kinds(shapes, "circle", "search")
        assert len(bands) + len(rings) // 2 == sum(
            1 for s in specs if type(s).__name__ != "DistanceSpec"
        )
        for m in data["measurements"]:
            role = "pass" if m["passed"] else "fail"
            if "circle_px" in m:
                u, v, r = m["circle_px"]
                assert any(
                    _near((c["u"], c["v"]), (u, v)) and c["r"] == pytest.approx(r, abs=0.01)
                    for c in _kinds(shapes, "circle", role)
                ), m["name"]
            for point in m.get("points", []):
                assert any(
                    _near((p["u"], p["v"]), tuple(point)) for p in _kinds(shapes, "point", role)
                ), m["name"]
            if m["kind"] != "distance" and m["value"] is not None:
                assert any(t["text"].startswith(f"{m['name']} = ") for t in _kinds(shapes, "text"))
        if not passed:
            assert _kinds(shapes, "point", "fail") or _kinds(shapes, "circle", "fail")


def test_a_job_draws_fixture_frames_and_fixtured_rois_turned_with_the_part() -> None:
    case, passed, data = _run("fixtured_plate", "moved_b.png")
    assert passed
    job = case.inspection
    shapes = result_shapes(job, data, passed)
    steps = data["steps"]
    axes = _kinds(shapes, "axes", "frame")
    assert len(axes) == 2  # the frames "near" and "part"
    part = PartFrame(steps["part"]["u"], steps["part"]["v"], steps["part"]["angle"])
    # both frames start at the big hole: "near" along +u, "part" turned towards the small hole
    assert all(_near((a["u"], a["v"]), (part.u, part.v)) for a in axes)
    angles = sorted(math.atan2(a["x"][1] - a["v"], a["x"][0] - a["u"]) for a in axes)
    assert angles == pytest.approx(sorted([0.0, part.angle_rad]), abs=1e-3)
    # the magnet's ROI [44, 12, 12, 12] in the part frame: docs/configuration.md's formula
    expected = outline(roi_transform(part, (44, 12, 12, 12)), 12, 12)
    magnet = [
        s
        for s in _kinds(shapes, "polygon", "pass")
        if np.allclose(s["points"], expected, atol=0.01)
    ]
    assert magnet, "the magnet's fixtured ROI"
    # by hand, its first corner: the part-frame point (43.5, 11.5)
    c, s = math.cos(part.angle_rad), math.sin(part.angle_rad)
    corner = (part.u + 43.5 * c - 11.5 * s, part.v + 43.5 * s + 11.5 * c)
    assert _near(tuple(magnet[0]["points"][0]), corner, 0.02)
    # the features the locate steps found, the caliper's band and its width's span
    big = steps["big_hole"]["features"][0]
    assert any(_near((p["u"], p["v"]), (big["u"], big["v"])) for p in _kinds(shapes, "point"))
    assert _kinds(shapes, "polygon", "search")
    assert _kinds(shapes, "line")
    names = {t["text"] for t in _kinds(shapes, "text")}
    assert {"small_hole", "magnet", "near", "part"} <= names


def test_a_job_whose_fixture_was_not_made_draws_no_roi_for_the_steps_in_its_frame() -> None:
    case, passed, data = _run("fixtured_plate", "no_plate.png")
    assert not passed
    shapes = result_shapes(case.inspection, data, passed)
    assert not _kinds(shapes, "axes")
    assert not [t for t in _kinds(shapes, "text") if t["text"] in ("magnet", "small_hole")]


def test_shapes_are_capped_and_bad_data_draws_the_roi_only() -> None:
    case = _case("example_cell_magnet_check")
    assert result_shapes(case.inspection, {}, False) == [
        {"kind": "rect", "role": "fail", "x": 486, "y": 236, "w": 50, "h": 60}
    ]
    board = _case("commissioning_board")
    many = {"count": 5000, "of": 5000, "corners": [[float(i), 1.0] for i in range(5000)]}
    assert len(result_shapes(board.inspection, many, True)) == MAX_SHAPES
    nasty = {"features": [{"u": "x", "v": None}, {"u": float("nan"), "v": 1.0}, 7], "count": 3}
    assert result_shapes(_case("cap_locate_circle").inspection, nasty, True) == []
    assert result_shapes(object(), {"x": 1}, True) == []
