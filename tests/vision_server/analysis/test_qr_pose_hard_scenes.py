"""qr_pose on scenes harder than the bench's (issue 29 part 4): depth misregistered by (2, 1) px
and scaled by +0.5 %, on oblique views (30-45° off the code's normal), codes near the image
border, a code on a plate standing 8 cm off the wall behind it with a narrow margin, a
1280x720 D435-like stereo camera, depth with 10 % holes, and a lens with barrel distortion.
Rotation p95 <= 0.2° and translation p95 <= 0.5 mm on each family, without a sensor check
(nothing configured) and with its correction. On these views the code before issue 29 read
0.204° (unchecked) and 0.212° (checked) on the D435-like camera and 0.71 mm unchecked through
the distorted lens; after it, at most 0.166° and 0.19 mm."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
import pytest
from numpy.typing import NDArray

from geometry import invert_transform, rotation_angle
from vision_server.analysis import qr_pose

FloatArray = NDArray[np.float64]
SHIFT_PX = (2.0, 1.0)
SCALE_BIAS = 0.005
TEXT = "cellvision:station-1"
CENTRE = np.array([0.989, 0.0, 1.0])
CHECKED: dict[str, Any] = {
    # what a sensor check leaves: its fit ~0.15 px off the true shift, with its standard errors
    "depth_scale": 1.0 + SCALE_BIAS,
    "depth_shift_px": (2.15, 0.9),
    "depth_scale_std": 1e-4,
    "depth_shift_std_px": (0.15, 0.11),
    "corner_bias_px": -0.03,
}
SCENE = """
name: hard_scenes
seed: {seed}
surfaces:
  - {{name: floor, center: [0, 0], height: 0.0, size: [4, 4], color: 90}}
boxes:
  - {{name: wall, pose: {{xyz: [{wall_x}, 0, 0], rpy: [0, 0, 0]}}, size: [0.02, 3.0, 3.5],
      color: 150}}
qr_boards:
  - name: qr
    text: "{text}"
    side_m: 0.16
    margin_m: {margin}
    pose: {{xyz: [0.989, 0.0, 1.0], rpy: [1.5707963267948966, 0.0, -1.5707963267948966]}}
robot:
  world_from_base: {{xyz: [0, 0, 0]}}
  home: {{xyz: [0, 0, 1.0], rpy: [-1.5707963267948966, 0, -1.5707963267948966]}}
  workspace: {{min: [-3, -3, -1], max: [3, 3, 4]}}
cameras:
  - name: rgbd
    model: xtion
    mount: tool
    pose: {{xyz: [0, 0, 0]}}
    noise_sigma: 1.0
    intrinsics: {{width: {w}, height: {h}, fx: {f}, fy: {f}, cx: {cx}, cy: {cy}, dist: {dist}}}
    depth: {{misregistration_px: [{du}, {dv}], scale_bias: {bias}, fb_px_m: {fb},
             disparity_sigma_px: {sigma_d}, dropout: {dropout}, range_m: [0.3, 4.0]}}
"""


@dataclass(frozen=True)
class Family:
    """A kind of hard scene: the camera (size, focal length, stereo fb and disparity noise),
    the views (distance, tilt off the code's normal, how far off the image centre as a
    fraction of the half size), the plate (margin, stand-off from the wall) and holes."""

    name: str
    distance_m: tuple[float, float] = (0.6, 1.2)
    tilt_deg: tuple[float, float] = (0.0, 30.0)
    off_centre: float = 0.0
    size: tuple[int, int] = (640, 480)
    f_px: float = 570.3
    dist: tuple[float, float, float, float, float] = (0.0, 0.0, 0.0, 0.0, 0.0)
    fb_px_m: float = 43.5
    sigma_d_px: float = 0.06
    margin_m: float = 0.032
    standoff_m: float = 0.001
    dropout: float = 0.002


FAMILIES = (
    Family("oblique", tilt_deg=(30.0, 45.0)),
    Family("border", off_centre=0.85),
    Family("plate", tilt_deg=(0.0, 40.0), margin_m=0.012, standoff_m=0.08),
    Family(
        "d435",
        (0.6, 1.5),
        (0.0, 40.0),
        off_centre=0.5,
        size=(1280, 720),
        f_px=910.0,
        fb_px_m=0.05 * 910.0,
        sigma_d_px=0.08,
    ),
    Family("holes", dropout=0.1),
    Family("distortion", off_centre=0.6, dist=(-0.08, 0.05, 0.0004, -0.0003, 0.0)),
)


def _cell(family: Family) -> Any:
    from simulation import SimCell, scene_from_text

    w, h = family.size
    text = SCENE.format(
        seed=7,
        wall_x=0.989 + family.standoff_m + 0.01,
        text=TEXT,
        margin=family.margin_m,
        w=w,
        h=h,
        f=family.f_px,
        cx=(w - 1) / 2,
        cy=(h - 1) / 2,
        dist=list(family.dist),
        du=SHIFT_PX[0],
        dv=SHIFT_PX[1],
        bias=SCALE_BIAS,
        fb=family.fb_px_m,
        sigma_d=family.sigma_d_px,
        dropout=family.dropout,
    )
    return SimCell(scene_from_text(text, source="hard_scenes.yaml"), seed=7)


def _view(rng: np.random.Generator, family: Family) -> FloatArray:
    """world_from_camera: the camera ``distance_m`` from the code's centre, ``tilt_deg`` off its
    normal in a random direction, rolled at random, and turned so that the code's centre lands
    up to ``off_centre`` of the half image off the principal point."""
    tilt = np.radians(rng.uniform(*family.tilt_deg))
    azimuth = rng.uniform(0.0, 2 * np.pi)
    direction = np.cos(tilt) * np.array([-1.0, 0.0, 0.0]) + np.sin(tilt) * np.array(
        [0.0, np.cos(azimuth), np.sin(azimuth)]
    )
    eye = CENTRE + rng.uniform(*family.distance_m) * direction
    z = (CENTRE - eye) / np.linalg.norm(CENTRE - eye)
    up = np.array([0.0, 0.0, 1.0])
    y = -(up - (up @ z) * z)
    y /= np.linalg.norm(y)
    x = np.cross(y, z)
    roll = rng.uniform(-np.pi, np.pi)
    x, y = np.cos(roll) * x + np.sin(roll) * y, -np.sin(roll) * x + np.cos(roll) * y
    rotation = np.column_stack([x, y, z])
    if family.off_centre > 0:
        angle = rng.uniform(0.0, 2 * np.pi)
        r = family.off_centre * rng.uniform(0.6, 1.0)
        w, h = family.size
        ray = np.array([r * np.cos(angle) * w / 2, r * np.sin(angle) * h / 2, family.f_px])
        ray /= np.linalg.norm(ray)
        # turn the camera so that its ray ``ray`` points at the code's centre
        axis = np.cross(ray, [0.0, 0.0, 1.0])
        s, c = float(np.linalg.norm(axis)), float(ray[2])
        k = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]]) / s
        rotation = rotation @ (np.eye(3) + s * k + (1 - c) * k @ k)
    pose = np.eye(4)
    pose[:3, :3] = rotation
    pose[:3, 3] = eye
    return pose


def _errors(family: Family, views: int, frames: int) -> dict[str, tuple[list[float], list[float]]]:
    cell = _cell(family)
    rng = np.random.default_rng(29)
    out: dict[str, tuple[list[float], list[float]]] = {"unchecked": ([], []), "checked": ([], [])}
    w, h = family.size
    done = 0
    while done < views:
        cell.world.base_from_tool = _view(rng, family)
        rendered = [cell.render("rgbd") for _ in range(frames)]
        frame = rendered[0]
        code = frame.truth.qr_codes["qr"]
        uv = code.corners_uv
        if not (np.all(uv >= 2) and np.all(uv[:, 0] < w - 2) and np.all(uv[:, 1] < h - 2)):
            continue  # the code (partly) outside the image
        done += 1
        truth_inv = invert_transform(code.camera_from_qr)
        for label, kw in (("unchecked", {}), ("checked", CHECKED)):
            pose = qr_pose(
                frame.color,
                [f.depth for f in rendered],
                frame.truth.intrinsics,
                expect=TEXT,
                side_m=0.16,
                **kw,
            )
            e = truth_inv @ pose.camera_from_qr
            out[label][0].append(float(np.linalg.norm(e[:3, 3])))
            out[label][1].append(float(np.degrees(rotation_angle(e[:3, :3]))))
    return out


@pytest.fixture(scope="module")
def hard_errors() -> dict[str, dict[str, tuple[list[float], list[float]]]]:
    """Per family and path: translation errors (m) and rotation errors (deg)."""
    return {
        family.name: _errors(family, 6 if family.size[0] > 640 else 8, 3) for family in FAMILIES
    }


@pytest.mark.parametrize("path", ["unchecked", "checked"])
@pytest.mark.parametrize("family", [f.name for f in FAMILIES])
def test_hard_scenes_meet_the_goal(hard_errors: dict[str, Any], family: str, path: str) -> None:
    # each kind of scene on its own (see the module's docstring for the figures before)
    t, r = hard_errors[family][path]
    assert len(t) == (6 if family == "d435" else 8)  # every view measured
    assert float(np.percentile(r, 95)) <= 0.2
    assert float(np.percentile(t, 95)) <= 0.0005
