"""Rendered features sit where the ground truth says, to a fraction of a pixel."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
from pyzbar import pyzbar

from geometry import rotation_angle, transform_points
from simulation import SimCell, scene_from_text

from .conftest import BOARD_SCENE, EXAMPLE_SCENE, cap_scene


def _blob_centroid(image: np.ndarray, top_level: float) -> tuple[np.ndarray, float]:
    """Coverage-weighted centroid (u, v) and area (px) of a bright blob on a black background."""
    alpha = np.clip((image.astype(np.float64) - 1.0) / (top_level - 1.0), 0.0, 1.0)
    v, u = np.mgrid[0 : image.shape[0], 0 : image.shape[1]]
    area = alpha.sum()
    return np.array([(alpha * u).sum() / area, (alpha * v).sum() / area]), float(area)


def _projected_disc(cell: SimCell, n: int = 4096) -> tuple[np.ndarray, float]:
    """Exact centroid and area of the image of the cap's top circle (shoelace on 4096 points)."""
    spec = cell.scene.part("cap")
    pose = cell.world.part_pose("cap")
    a = np.linspace(0, 2 * np.pi, n, endpoint=False)
    circle = np.column_stack(
        [spec.radius * np.cos(a), spec.radius * np.sin(a), np.full(n, spec.height)]
    )
    camera_from_world = np.linalg.inv(cell.world_from_camera("cam"))
    uv = cell.scene.camera("cam").intrinsics.project(
        transform_points(camera_from_world @ pose, circle)
    )
    x, y = uv[:, 0], uv[:, 1]
    xn, yn = np.roll(x, -1), np.roll(y, -1)
    cross = x * yn - xn * y
    area = cross.sum() / 2
    return np.array([((x + xn) * cross).sum(), ((y + yn) * cross).sum()]) / (6 * area), abs(area)


@pytest.mark.parametrize(("x", "y"), [(0.05, -0.03), (-0.071, 0.0433)])
def test_cap_disc_centroid_matches_ground_truth(x: float, y: float) -> None:
    cell = SimCell(cap_scene(x, y))
    frame = cell.render("cam")
    truth = frame.truth.features["cap.top_centre"]
    assert truth.visible
    top_level = float(np.max(frame.color))
    centroid, area = _blob_centroid(frame.color, top_level)
    # Fronto-parallel circle, no distortion: its image's centroid is the projected centre.
    assert np.linalg.norm(centroid - truth.uv) < 0.1
    _, exact_area = _projected_disc(cell)
    assert area == pytest.approx(exact_area, rel=0.005)


def test_cap_disc_with_distortion_matches_exact_projection() -> None:
    cell = SimCell(cap_scene(0.09, 0.07, k1=-0.25))
    frame = cell.render("cam")
    centroid, area = _blob_centroid(frame.color, float(np.max(frame.color)))
    exact_centroid, exact_area = _projected_disc(cell)
    assert np.linalg.norm(centroid - exact_centroid) < 0.1
    assert area == pytest.approx(exact_area, rel=0.005)
    # Strong distortion near the corner moves the blob centroid away from the projected centre
    # (physics, not a rendering error): locators must undistort before taking centroids.
    bias = np.linalg.norm(frame.truth.features["cap.top_centre"].uv - exact_centroid)
    assert 0.05 < bias < 1.0


def test_labels_and_masks() -> None:
    cell = SimCell(cap_scene())
    frame = cell.render("cam")
    mask = frame.truth.mask("cap")
    uv = frame.truth.features["cap.top_centre"].uv
    assert mask[int(round(uv[1])), int(round(uv[0]))]
    assert frame.truth.mask("belt")[0, 0]
    assert not frame.truth.mask("nothing").any()


def test_qr_code_decodes_and_corners_match(board_cell: SimCell) -> None:
    frame = board_cell.render("rgbd")
    qr = frame.truth.qr_codes["qr"]
    assert qr.visible
    # Camera 1 m in front of the board, looking at it: camera_from_qr has z about 1 m.
    assert qr.camera_from_qr[2, 3] == pytest.approx(0.989, abs=1e-6)
    gray = cv2.cvtColor(frame.color, cv2.COLOR_BGR2GRAY)

    decoded = pyzbar.decode(gray)
    assert [d.data for d in decoded] == [b"cellvision:test"]
    zbar_pts = np.array([(p.x, p.y) for p in decoded[0].polygon], dtype=np.float64)
    for corner in qr.corners_uv:
        assert np.min(np.linalg.norm(zbar_pts - corner, axis=1)) < 1.0

    text, points, _ = cv2.QRCodeDetector().detectAndDecode(gray)
    assert text == "cellvision:test"
    pts = points.reshape(-1, 2)
    errors = [np.min(np.linalg.norm(pts - c, axis=1)) for c in qr.corners_uv]
    # OpenCV's detector reports whole-pixel corners about a pixel inside the symbol.
    assert max(errors) < 2.0


@pytest.mark.parametrize("distance", [0.6, 1.4])
def test_qr_decodes_across_the_working_range(board_cell: SimCell, distance: float) -> None:
    pose = board_cell.robot.tool_pose()
    pose[0, 3] = 0.989 - distance
    board_cell.robot.move_linear(pose)
    frame = board_cell.render("rgbd")
    qr = frame.truth.qr_codes["qr"]
    decoded = pyzbar.decode(cv2.cvtColor(frame.color, cv2.COLOR_BGR2GRAY))
    assert [d.data for d in decoded] == [b"cellvision:test"]
    zbar_pts = np.array([(p.x, p.y) for p in decoded[0].polygon], dtype=np.float64)
    for corner in qr.corners_uv:
        assert np.min(np.linalg.norm(zbar_pts - corner, axis=1)) < 1.0


def test_qr_module_edges_are_exact(board_cell: SimCell) -> None:
    """The left edge of the code, measured from pixel coverage, lies on the c0-c3 line."""
    board_cell.scene.camera("rgbd")
    frame = board_cell.render("rgbd")
    qr = frame.truth.qr_codes["qr"]
    gray = cv2.cvtColor(frame.color, cv2.COLOR_BGR2GRAY).astype(np.float64)
    c0, c3 = qr.corners_uv[0], qr.corners_uv[3]
    edges = []
    for v in range(int(np.ceil(c0[1])) + 1, int(np.floor(c0[1])) + 3):  # inside the top finder row
        u_edge = c0[0] + (c3[0] - c0[0]) * (v - c0[1]) / (c3[1] - c0[1])
        k = int(np.floor(u_edge + 0.5))  # the pixel that contains the edge
        light = gray[v, k - 4 : k - 1].mean()
        dark = gray[v, k + 1 : k + 3].mean()
        dark_fraction = (light - gray[v, k]) / (light - dark)
        edges.append((k + 0.5 - dark_fraction) - u_edge)
    assert abs(np.mean(edges)) < 0.1


def test_camera_pose_truth_is_consistent(example_cell: SimCell) -> None:
    frame = example_cell.render("tool_camera")
    t = frame.truth
    np.testing.assert_allclose(t.world_from_base @ t.base_from_camera, t.world_from_camera)
    tool_from_camera = example_cell.scene.camera("tool_camera").pose
    np.testing.assert_allclose(t.base_from_tool @ tool_from_camera, t.base_from_camera, atol=1e-12)
    for f in t.features.values():
        if f.in_image:
            p_camera = transform_points(np.linalg.inv(t.world_from_camera), f.p_world)
            np.testing.assert_allclose(p_camera, f.p_camera, atol=1e-12)
    for q in t.qr_codes.values():
        rot = q.world_from_qr[:3, :3]
        assert rotation_angle(rot.T @ rot) < 1e-12
        # The QR frame follows the paper: x = (c0 - c3)/|..|, y = (c2 - c3)/|..|, origin = mean.
        c = q.corners_world
        np.testing.assert_allclose(
            rot[:, 0], (c[0] - c[3]) / np.linalg.norm(c[0] - c[3]), atol=1e-12
        )
        np.testing.assert_allclose(
            rot[:, 1], (c[2] - c[3]) / np.linalg.norm(c[2] - c[3]), atol=1e-12
        )
        np.testing.assert_allclose(q.world_from_qr[:3, 3], c.mean(axis=0), atol=1e-12)


def test_determinism() -> None:
    scene = scene_from_text(BOARD_SCENE)
    x, y, z = SimCell(scene, seed=1), SimCell(scene, seed=1), SimCell(scene, seed=2)
    fx, fy, fz = x.render("rgbd"), y.render("rgbd"), z.render("rgbd")
    np.testing.assert_array_equal(fx.color, fy.color)
    assert fx.depth is not None
    assert fy.depth is not None
    assert fz.depth is not None
    np.testing.assert_array_equal(fx.depth, fy.depth)
    assert not np.array_equal(fx.color, fz.color)
    assert not np.array_equal(fx.depth, fz.depth)
    # Successive frames of one camera get fresh noise, the same for the same seed.
    gx, gy = x.render("rgbd"), y.render("rgbd")
    assert not np.array_equal(fx.color, gx.color)
    np.testing.assert_array_equal(gx.color, gy.color)
    # Jittered part placement also follows the seed.
    a = SimCell.from_yaml(EXAMPLE_SCENE, seed=9)
    b = SimCell.from_yaml(EXAMPLE_SCENE, seed=9)
    c = SimCell.from_yaml(EXAMPLE_SCENE, seed=10)
    np.testing.assert_array_equal(a.world.part_pose("cap_1"), b.world.part_pose("cap_1"))
    assert not np.array_equal(a.world.part_pose("cap_1"), c.world.part_pose("cap_1"))
