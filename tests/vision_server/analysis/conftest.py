"""Synthetic QR images with exactly known corners, for the QR reader and pose tests."""

from __future__ import annotations

import cv2
import numpy as np
from numpy.typing import NDArray

SUPERSAMPLE = 4


def qr_modules(text: str) -> NDArray[np.uint8]:
    """The code's modules (N, N), 1 = dark, without quiet zone (cv2.QRCodeEncoder)."""
    img = cv2.QRCodeEncoder.create().encode(text)
    dark = (img < 128).astype(np.uint8)
    rows = np.flatnonzero(dark.any(axis=1))
    cols = np.flatnonzero(dark.any(axis=0))
    return dark[rows[0] : rows[-1] + 1, cols[0] : cols[-1] + 1]


def render_qr(
    text: str,
    corners_uv: NDArray[np.float64],
    size: tuple[int, int] = (640, 480),
    *,
    mirror: bool = False,
    dark: int = 30,
    light: int = 220,
    background: int = 120,
    blur_sigma: float = 0.0,
    noise_sigma: float = 0.0,
    seed: int = 0,
) -> NDArray[np.uint8]:
    """A gray image (H, W) of the code whose symbol corners c0..c3 (as printed: top-left,
    top-right, bottom-right, bottom-left of the dark-module boundary) land at ``corners_uv``.

    A white quiet zone of 4 modules surrounds the code. ``mirror`` shows the code mirrored
    left-right (as in a mirror): ``corners_uv`` are then the image positions of the printed
    c1, c0, c3, c2. Rendered at 4x and area-averaged down.
    """
    modules = qr_modules(text)
    if mirror:
        modules = modules[:, ::-1]
    n = modules.shape[0]
    q = 4
    px = 16  # pixels per module in the source
    src = np.full(((n + 2 * q) * px, (n + 2 * q) * px), light, np.uint8)
    big = np.kron(modules, np.ones((px, px), np.uint8))
    src[q * px : (q + n) * px, q * px : (q + n) * px] = np.where(big > 0, dark, light)
    # source pixel-centre coordinates of the symbol's outer corners
    lo, hi = q * px - 0.5, (q + n) * px - 0.5
    src_corners = np.array([[lo, lo], [hi, lo], [hi, hi], [lo, hi]], np.float64)
    s = SUPERSAMPLE
    dst = (np.asarray(corners_uv, np.float64) + 0.5) * s - 0.5
    h = cv2.getPerspectiveTransform(src_corners.astype(np.float32), dst.astype(np.float32))
    w, hgt = size
    out = cv2.warpPerspective(
        src,
        h,
        (w * s, hgt * s),
        flags=cv2.INTER_LINEAR,
        borderMode=cv2.BORDER_CONSTANT,
        borderValue=background,
    )
    img = cv2.resize(out, (w, hgt), interpolation=cv2.INTER_AREA).astype(np.float64)
    if blur_sigma > 0:
        img = cv2.GaussianBlur(img, (0, 0), blur_sigma)
    if noise_sigma > 0:
        img = img + np.random.default_rng(seed).normal(0, noise_sigma, img.shape)
    return np.clip(np.rint(img), 0, 255).astype(np.uint8)


def square_corners(
    centre: tuple[float, float], side: float, angle_deg: float = 0.0
) -> NDArray[np.float64]:
    """c0..c3 of an upright square code rotated by ``angle_deg`` (clockwise on screen)."""
    a = np.deg2rad(angle_deg)
    r = np.array([[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]])
    h = side / 2
    local = np.array([[-h, -h], [h, -h], [h, h], [-h, h]])
    result: NDArray[np.float64] = local @ r.T + np.asarray(centre)
    return result


# --- the simulated cell: an RGB-D camera in front of a QR board -----------------------------

QR_SCENE = """
name: qr_pose_test
seed: {seed}
surfaces:
  - {{name: floor, center: [0, 0], height: 0.0, size: [4, 4], color: 90}}
boxes:
  - {{name: wall, pose: {{xyz: [1.0, 0, 0], rpy: [0, 0, 0]}}, size: [0.02, 2.0, 2.5], color: 150}}
qr_boards:
  - name: qr
    text: "cellvision:station-1"
    side_m: 0.16
    pose: {{xyz: [0.989, 0.0, 1.0], rpy: [1.5707963267948966, 0.0, -1.5707963267948966]}}
robot:
  world_from_base: {{xyz: [0, 0, 0]}}
  home: {{xyz: [0, 0, 1.0], rpy: [-1.5707963267948966, 0, -1.5707963267948966]}}
  workspace: {{min: [-2, -2, -1], max: [2, 2, 3]}}
cameras:
  - name: rgbd
    model: xtion
    mount: tool
    pose: {{xyz: [0, 0, 0]}}
    noise_sigma: 1.0
    depth: {{misregistration_px: [{mis_u}, {mis_v}], scale_bias: {bias}}}
"""

QR_BOARD_CENTRE = np.array([0.989, 0.0, 1.0])


def qr_cell(
    seed: int = 5, misregistration_px: tuple[float, float] = (0.0, 0.0), scale_bias: float = 0.0
):  # type: ignore[no-untyped-def]
    """A SimCell with an Xtion-like RGB-D camera on the tool, facing a 0.16 m QR board."""
    from simulation import SimCell, scene_from_text

    text = QR_SCENE.format(
        seed=seed, mis_u=misregistration_px[0], mis_v=misregistration_px[1], bias=scale_bias
    )
    return SimCell(scene_from_text(text, source="qr_pose_test.yaml"), seed=seed)


def random_view(
    rng: np.random.Generator, distance: tuple[float, float] = (0.7, 1.3), max_tilt_deg: float = 35
) -> NDArray[np.float64]:
    """world_from_camera looking at the board from a random direction and distance, the code
    somewhere in the middle of the image and a random roll."""
    tilt = np.deg2rad(rng.uniform(0, max_tilt_deg))
    az = rng.uniform(0, 2 * np.pi)
    normal = np.array([-1.0, 0.0, 0.0])  # out of the board, towards the viewer
    a = np.array([0.0, np.cos(az), np.sin(az)])
    direction = np.cos(tilt) * normal + np.sin(tilt) * a
    eye = QR_BOARD_CENTRE + rng.uniform(*distance) * direction
    target = QR_BOARD_CENTRE + np.array([0.0, *rng.uniform(-0.08, 0.08, 2)])
    z = target - eye
    z /= np.linalg.norm(z)
    up = np.array([0.0, 0.0, 1.0])
    yv = -(up - (up @ z) * z)
    yv /= np.linalg.norm(yv)
    roll = rng.uniform(-np.pi, np.pi)
    x = np.cross(yv, z)
    c, s = np.cos(roll), np.sin(roll)
    x, yv = c * x + s * yv, -s * x + c * yv
    t = np.eye(4)
    t[:3, :3] = np.column_stack([x, yv, z])
    t[:3, 3] = eye
    return t
