"""Scenes harder than the station's, for ``qr_pose`` under a real depth sensor's errors
(issue 29): the bench's calibration section and the tests draw their views from here.

A :class:`HardFamily` is a kind of scene (camera, views, code, depth holes); :func:`hard_views`
renders views of one with the depth misregistered by ``shift_px`` (du, dv pixels) and scaled
by ``1 + scale_bias``, each with its true ``camera_from_qr`` (metres, OpenCV camera frame).
"""

from __future__ import annotations

import dataclasses
from typing import Any

import numpy as np
from numpy.typing import NDArray

from geometry import make_transform
from simulation.cell import SimCell
from simulation.scene import scene_from_text

__all__ = ["HARD_CENTRE", "HardFamily", "hard_cell", "hard_view", "hard_views"]

FloatArray = NDArray[np.float64]

_SCENE = """
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
    side_m: {side}
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
             disparity_sigma_px: {sigma_d}, dropout: {dropout}, range_m: [{near}, 4.0]}}
"""
HARD_CENTRE = np.array([0.989, 0.0, 1.0])


@dataclasses.dataclass(frozen=True)
class HardFamily:
    """A kind of scene harder than the station's: the camera (size, focal length, distortion,
    stereo fb and disparity noise, near range), the views (distance, tilt off the code's
    normal, the code's centre up to ``off_centre`` of the half image off the principal point),
    the code (side, margin of its plate, the plate's stand-off from the wall) and depth holes.
    ``goal``: judged against the goal (False: reported only, see the table's note)."""

    name: str
    distance_m: tuple[float, float] = (0.6, 1.2)
    tilt_deg: tuple[float, float] = (0.0, 30.0)
    off_centre: float = 0.0
    size: tuple[int, int] = (640, 480)
    f_px: float = 570.3
    dist: tuple[float, float, float, float, float] = (0.0, 0.0, 0.0, 0.0, 0.0)
    fb_px_m: float = 43.5
    sigma_d_px: float = 0.06
    near_m: float = 0.3
    side_m: float = 0.16
    margin_m: float = 0.032
    standoff_m: float = 0.001
    dropout: float = 0.002
    goal: bool = True


def hard_cell(
    family: HardFamily, shift_px: tuple[float, float], scale_bias: float, text: str
) -> SimCell:
    """The simulated cell of ``family``: its RGB-D camera ``rgbd`` on the robot's tool, depth
    misregistered by ``shift_px`` and scaled by ``1 + scale_bias``, the code reading ``text``."""
    w, h = family.size
    scene = _SCENE.format(
        seed=7,
        wall_x=0.989 + family.standoff_m + 0.01,
        text=text,
        side=family.side_m,
        margin=family.margin_m,
        w=w,
        h=h,
        f=family.f_px,
        cx=(w - 1) / 2,
        cy=(h - 1) / 2,
        dist=list(family.dist),
        du=shift_px[0],
        dv=shift_px[1],
        bias=scale_bias,
        fb=family.fb_px_m,
        sigma_d=family.sigma_d_px,
        dropout=family.dropout,
        near=family.near_m,
    )
    return SimCell(scene_from_text(scene, source="hard_scenes.yaml"), seed=7)


def hard_view(rng: np.random.Generator, family: HardFamily) -> FloatArray:
    """world_from_camera: ``distance_m`` from the code's centre, ``tilt_deg`` off its normal
    in a random direction, a random roll, turned so that the code's centre lands up to
    ``off_centre`` of the half image off the principal point."""
    tilt = np.radians(rng.uniform(*family.tilt_deg))
    azimuth = rng.uniform(0.0, 2 * np.pi)
    direction = np.cos(tilt) * np.array([-1.0, 0.0, 0.0]) + np.sin(tilt) * np.array(
        [0.0, np.cos(azimuth), np.sin(azimuth)]
    )
    eye = HARD_CENTRE + rng.uniform(*family.distance_m) * direction
    z = (HARD_CENTRE - eye) / np.linalg.norm(HARD_CENTRE - eye)
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
        axis = np.cross(ray, [0.0, 0.0, 1.0])  # turn the camera's ray `ray` onto the code
        s, c = float(np.linalg.norm(axis)), float(ray[2])
        k = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]]) / s
        rotation = rotation @ (np.eye(3) + s * k + (1 - c) * k @ k)
    return make_transform(rotation, eye)


def hard_views(
    family: HardFamily,
    count: int,
    *,
    seed: int,
    frames: int,
    shift_px: tuple[float, float],
    scale_bias: float,
    text: str,
) -> list[tuple[Any, list[Any], FloatArray]]:
    """``count`` views of ``family`` (the first frame, the depth of ``frames`` frames, the
    true camera_from_qr) with the code wholly in the image; views with the code (partly)
    outside it are drawn again, ``10 * count`` tries at most."""
    cell = hard_cell(family, shift_px, scale_bias, text)
    rng = np.random.default_rng(seed)
    w, h = family.size
    out: list[tuple[Any, list[Any], FloatArray]] = []
    tries = 0
    while len(out) < count and tries < 10 * count:
        tries += 1
        cell.world.base_from_tool = hard_view(rng, family)
        rendered = [cell.render("rgbd") for _ in range(frames)]
        code = rendered[0].truth.qr_codes.get("qr")
        if code is None:
            continue
        uv = code.corners_uv
        if not (np.all(uv >= 2) and np.all(uv[:, 0] < w - 2) and np.all(uv[:, 1] < h - 2)):
            continue
        out.append((rendered[0], [f.depth for f in rendered], code.camera_from_qr))
    return out
