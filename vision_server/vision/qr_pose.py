"""Pose of a QR code from its image corners and registered depth frames (paper, eqs. 1-4).

Frames and conventions of docs/conventions.md: the QR frame has ``x = (c0 - c3)/|c0 - c3|``
("up" on the printed code), ``y = (c2 - c3)/|c2 - c3|`` ("right"), ``z = x × y`` (into the
surface), origin at the mean of the four corners. The result is ``camera_from_qr`` (4x4 float64,
metres). Depth frames are uint16 millimetres registered to the colour image (same pixel grid as
the corners), 0 = no depth; depth is z-depth (along the optical axis), as depth cameras report.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Literal

import cv2
import numpy as np
from numpy.typing import ArrayLike, NDArray

from geometry import CameraIntrinsics, fit_plane
from vision_server.vision._checks import check_depth
from vision_server.vision.errors import DepthError, ParameterError

__all__ = ["QrPose", "QrPoseQuality", "qr_pose"]

FloatArray = NDArray[np.float64]
_MAX_RANSAC_POINTS = 5000


@dataclass(frozen=True)
class QrPoseQuality:
    """How much to trust a QR pose.

    Attributes
    ----------
    method : str
        ``"plane"`` or ``"corners"``.
    n_frames : int
        Number of depth frames used.
    corner_depth_std_m : (4,) ndarray of float64
        Spread (standard deviation) of the valid depth values in each corner's window over all
        frames, metres (NaN for a corner without depth when the method does not need it).
    corner_valid_fraction : (4,) ndarray of float64
        Fraction of valid (non-zero) depth values in each corner's window over all frames.
    valid_depth_fraction : float
        Fraction of valid depth values over the code's surface (pixels inside the corner
        quadrilateral) and all frames.
    plane_rms_m : float or None
        RMS point-to-plane distance of the plane's inliers, metres (``plane`` method only).
    inlier_fraction : float or None
        Fraction of the valid surface points within the RANSAC threshold (``plane`` only).
    orthogonality_error_rad : float
        Angle between the raw axes ``c0 - c3`` and ``c2 - c3`` (3-D, before orthonormalisation)
        minus 90 degrees, radians.
    side_lengths_m : (4,) ndarray of float64
        Measured 3-D side lengths ``|c0c1|, |c1c2|, |c2c3|, |c3c0|``, metres.
    side_m : float or None
        The printed side length given by the caller, metres.
    side_error_m : float or None
        Largest ``|side_length - side_m|``, metres (None without ``side_m``).
    """

    method: str
    n_frames: int
    corner_depth_std_m: FloatArray
    corner_valid_fraction: FloatArray
    valid_depth_fraction: float
    plane_rms_m: float | None
    inlier_fraction: float | None
    orthogonality_error_rad: float
    side_lengths_m: FloatArray
    side_m: float | None
    side_error_m: float | None


@dataclass(frozen=True)
class QrPose:
    """The pose of a QR code in the camera frame.

    Attributes
    ----------
    camera_from_qr : (4, 4) ndarray of float64
        Maps points in the QR frame to the camera frame (metres).
    corners_camera : (4, 3) ndarray of float64
        The 3-D corners c0..c3 in the camera frame, metres.
    quality : QrPoseQuality
        The quality report.
    """

    camera_from_qr: FloatArray
    corners_camera: FloatArray
    quality: QrPoseQuality


def _check_corners(corners: ArrayLike, shape: tuple[int, int]) -> FloatArray:
    try:
        c = np.asarray(corners, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise ParameterError(f"corners must be a (4, 2) array of (u, v) pixels: {exc}") from exc
    if c.shape != (4, 2) or not np.all(np.isfinite(c)):
        raise ParameterError(f"corners must be a finite (4, 2) array of (u, v), got {c.shape}")
    height, width = shape
    for k, (u, v) in enumerate(c):
        if not (-0.5 <= u < width - 0.5 and -0.5 <= v < height - 0.5):
            raise ParameterError(
                f"corner c{k} at (u={u:.1f}, v={v:.1f}) is outside the {width}x{height} depth image"
            )
    return c


def _stack_depth(
    depth_frames: Sequence[NDArray[np.uint16]] | NDArray[np.uint16],
) -> NDArray[np.uint16]:
    frames = (
        [depth_frames]
        if isinstance(depth_frames, np.ndarray) and depth_frames.ndim == 2
        else list(depth_frames)
    )
    if not frames:
        raise ParameterError("depth_frames is empty: at least one depth frame is needed")
    checked = [check_depth(f, name=f"depth frame {i}") for i, f in enumerate(frames)]
    shape = checked[0].shape
    for i, f in enumerate(checked):
        if f.shape != shape:
            raise ParameterError(f"depth frame {i} has shape {f.shape}, frame 0 has {shape}")
    return np.stack(checked)


def _corner_depths(
    stack: NDArray[np.uint16], corners: FloatArray, window: int
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Mean depth (m), its std (m) and the valid fraction in each corner's window, all frames."""
    _, height, width = stack.shape
    means, stds, fractions = np.full(4, np.nan), np.full(4, np.nan), np.zeros(4)
    for k, (u, v) in enumerate(corners):
        cu, cv_ = int(round(u)), int(round(v))
        u0, u1 = max(cu - window, 0), min(cu + window + 1, width)
        v0, v1 = max(cv_ - window, 0), min(cv_ + window + 1, height)
        values = stack[:, v0:v1, u0:u1].astype(np.float64).ravel()
        valid = values[values > 0] / 1000.0
        fractions[k] = valid.size / values.size
        if valid.size:
            means[k] = float(valid.mean())
            stds[k] = float(valid.std())
    return means, stds, fractions


def _rotation_from_corners(p: FloatArray) -> tuple[FloatArray, float]:
    """Rotation (columns x, y, z) and orthogonality error from 3-D corners, paper eqs. 1-3.

    x is exactly eq. 1, z is eq. 3 and y = z × x completes a right-handed orthonormal frame.
    """
    x_raw, y_raw = p[0] - p[3], p[2] - p[3]
    x = x_raw / np.linalg.norm(x_raw)
    y = y_raw / np.linalg.norm(y_raw)
    ortho = float(np.arccos(np.clip(x @ y, -1.0, 1.0)) - np.pi / 2)
    z = np.cross(x, y)
    z /= np.linalg.norm(z)
    return np.column_stack([x, np.cross(z, x), z]), ortho


def _ideal_square(side: float) -> FloatArray:
    """Corners c0..c3 of an ideal code of ``side`` metres in its own QR frame."""
    h = side / 2.0
    return np.array([[h, -h, 0.0], [h, h, 0.0], [-h, h, 0.0], [-h, -h, 0.0]])


def _rotation_best_fit(p: FloatArray) -> FloatArray:
    """Rotation that best maps the ideal square onto the corners ``p`` (Kabsch, least squares)."""
    side = float(np.mean(np.linalg.norm(p - np.roll(p, -1, axis=0), axis=1)))
    model = _ideal_square(side)
    centred = p - p.mean(axis=0)
    u, _, vt = np.linalg.svd(centred.T @ model)
    d = np.sign(np.linalg.det(u @ vt))
    return np.asarray(u @ np.diag([1.0, 1.0, d]) @ vt, dtype=np.float64)


def _surface_points(
    stack: NDArray[np.uint16], corners: FloatArray, intrinsics: CameraIntrinsics
) -> tuple[FloatArray, float]:
    """3-D points (camera frame, metres) of every valid depth pixel inside the quadrilateral."""
    _, height, width = stack.shape
    mask = np.zeros((height, width), np.uint8)
    shift = 4
    poly = np.round((corners) * (1 << shift)).astype(np.int32)
    cv2.fillConvexPoly(mask, poly, 1, lineType=cv2.LINE_8, shift=shift)
    vs, us = np.nonzero(mask)
    if vs.size == 0:
        raise DepthError("the QR code's quadrilateral covers no depth pixel")
    depth = stack[:, vs, us].astype(np.float64) / 1000.0  # (N, P)
    valid = depth > 0
    fraction = float(valid.mean())
    xy = intrinsics.undistort_pixels(np.column_stack([us, vs]).astype(np.float64))
    xy_all = np.broadcast_to(xy[None], (stack.shape[0], *xy.shape))[valid]
    z = depth[valid]
    return np.column_stack([xy_all[:, 0] * z, xy_all[:, 1] * z, z]), fraction


def _fit_inverse_depth(points: FloatArray) -> tuple[FloatArray, float]:
    """Plane ``normal . p + d = 0`` (unit normal towards the camera) by least squares on 1/z.

    A depth camera's noise lies along the rays, mostly in disparity (proportional to 1/z), not
    perpendicular to the plane: a total-least-squares fit of the 3-D points is then biased for
    a tilted plane (by about 0.1 degree at 1 m with Kinect-like noise). On a plane, 1/z is
    linear in the normalised image coordinates (x/z, y/z), which carry no depth noise, so an
    ordinary least-squares fit of 1/z is the right model.
    """
    z = points[:, 2]
    design = np.column_stack([points[:, 0] / z, points[:, 1] / z, np.ones_like(z)])
    abc, *_ = np.linalg.lstsq(design, 1.0 / z, rcond=None)
    d = 1.0 / float(np.linalg.norm(abc))
    return np.asarray(-abc * d, dtype=np.float64), d


def qr_pose(
    depth_frames: Sequence[NDArray[np.uint16]] | NDArray[np.uint16],
    corners: ArrayLike,
    intrinsics: CameraIntrinsics,
    *,
    method: Literal["plane", "corners"] = "plane",
    side_m: float | None = None,
    corner_window: int = 1,
    ransac_threshold_m: float = 0.008,
    min_valid_fraction: float = 0.25,
    min_points: int = 50,
) -> QrPose:
    """``camera_from_qr`` from the code's image corners and N registered depth frames.

    Methods
    -------
    ``corners`` (the paper's): the depth at each corner is the mean of the valid (non-zero)
    values in a ``(2*corner_window + 1)``-pixel square window around it over all frames
    (``corner_window=0`` is the paper's single pixel); each corner is back-projected with its
    depth; the axes follow eqs. 1-3 (x exact, y = z × x to make the frame orthonormal) and the
    origin is the mean of the corners (eq. 4).

    ``plane`` (default): a RANSAC plane is fitted to the valid depth pixels inside the corner
    quadrilateral, all frames pooled (100 RANSAC draws among at most 5000 of the points), then
    refitted on all inliers by least squares on inverse depth (the noise model of structured-
    light and stereo depth cameras, see ``_fit_inverse_depth``); the rays of the sub-pixel
    corners are intersected with the plane; the rotation is the least-squares fit of an ideal
    square to the four 3-D corners (so all four
    corners count, and the axes are orthonormal by construction); the origin is the mean of
    the corners (eq. 4).

    Parameters
    ----------
    depth_frames : (H, W) uint16 ndarray or sequence of them
        Depth in millimetres registered to the colour image, 0 = no depth.
    corners : (4, 2) array_like of float
        c0..c3 in ``(u, v)`` pixels of the colour image (e.g. ``QrCode.corners``).
    intrinsics : geometry.CameraIntrinsics
        The colour camera's intrinsics (the corners are undistorted with them).
    side_m : float, optional
        The printed side length of the code in metres, for the quality report.
    corner_window : int
        Half-size in pixels of the corner depth window (both methods' corner statistics).
    ransac_threshold_m : float
        RANSAC inlier distance in metres (``plane``).
    min_valid_fraction : float
        Least fraction of valid depth pixels over the code's surface (``plane``).
    min_points : int
        Least number of valid surface points (``plane``).

    Raises
    ------
    DepthError
        A corner has no valid depth (``corners``), or too few valid depth pixels over the code
        (``plane``), or no plane could be fitted.
    ParameterError, BadImageError
        Malformed corners, options or depth frames.
    """
    if method not in ("plane", "corners"):
        raise ParameterError(f"method must be 'plane' or 'corners', got {method!r}")
    if corner_window < 0:
        raise ParameterError(f"corner_window must be >= 0, got {corner_window}")
    if side_m is not None and not side_m > 0:
        raise ParameterError(f"side_m must be positive, got {side_m!r}")
    stack = _stack_depth(depth_frames)
    uv = _check_corners(corners, (stack.shape[1], stack.shape[2]))
    depths, stds, fractions = _corner_depths(stack, uv, corner_window)

    plane_rms: float | None = None
    inlier_fraction: float | None = None
    if method == "corners":
        missing = [f"c{k}" for k in range(4) if not np.isfinite(depths[k])]
        if missing:
            raise DepthError(
                f"no valid depth at corner(s) {', '.join(missing)} in {stack.shape[0]} frame(s)"
                f" (window {2 * corner_window + 1}x{2 * corner_window + 1} px)"
            )
        p = intrinsics.backproject(uv, depths)
        rotation, ortho = _rotation_from_corners(p)
        valid_fraction = float(np.mean(fractions))
    else:
        points, valid_fraction = _surface_points(stack, uv, intrinsics)
        if valid_fraction < min_valid_fraction or points.shape[0] < min_points:
            raise DepthError(
                f"too few valid depth pixels on the QR code: {points.shape[0]} points, "
                f"{100 * valid_fraction:.0f}% valid (need {min_points} and "
                f"{100 * min_valid_fraction:.0f}%)"
            )
        rng = np.random.default_rng(0)
        sample = (
            points[rng.choice(points.shape[0], _MAX_RANSAC_POINTS, replace=False)]
            if points.shape[0] > _MAX_RANSAC_POINTS
            else points
        )
        try:
            first = fit_plane(
                sample, ransac_threshold_m=ransac_threshold_m, ransac_iterations=100, rng=rng
            )
        except ValueError as exc:
            raise DepthError(f"no plane could be fitted to the QR code's depth: {exc}") from exc
        residuals = points @ first.normal + first.d
        inliers = np.abs(residuals) <= ransac_threshold_m
        if int(inliers.sum()) < min_points:
            raise DepthError(
                f"only {int(inliers.sum())} depth points lie on the QR code's plane "
                f"(need {min_points})"
            )
        normal, d = _fit_inverse_depth(points[inliers])
        plane_rms = float(np.sqrt(np.mean((points[inliers] @ normal + d) ** 2)))
        inlier_fraction = float(inliers.mean())
        rays = intrinsics.pixel_rays(uv)
        denom = rays @ normal
        if np.any(np.abs(denom) < 1e-6):
            raise DepthError("a corner's ray is parallel to the QR code's plane")
        p = rays * (-d / denom)[:, None]
        _, ortho = _rotation_from_corners(p)
        rotation = _rotation_best_fit(p)

    sides = np.linalg.norm(p - np.roll(p, -1, axis=0), axis=1)
    camera_from_qr = np.eye(4)
    camera_from_qr[:3, :3] = rotation
    camera_from_qr[:3, 3] = p.mean(axis=0)
    quality = QrPoseQuality(
        method=method,
        n_frames=int(stack.shape[0]),
        corner_depth_std_m=stds,
        corner_valid_fraction=fractions,
        valid_depth_fraction=valid_fraction,
        plane_rms_m=plane_rms,
        inlier_fraction=inlier_fraction,
        orthogonality_error_rad=ortho,
        side_lengths_m=sides,
        side_m=None if side_m is None else float(side_m),
        side_error_m=None if side_m is None else float(np.max(np.abs(sides - side_m))),
    )
    return QrPose(camera_from_qr=camera_from_qr, corners_camera=p, quality=quality)
