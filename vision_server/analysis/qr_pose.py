"""QR pose from an RGB-D camera: ``camera_from_qr`` from one colour frame and N depth frames.

Frames and corner order are those of docs/conventions.md: QR frame x = (c0 - c3)/|..| (up on
the print), y = (c2 - c3)/|..| (right), z = x × y (into the surface), origin = mean of the
corners. Depth frames are uint16 millimetres (0 = no depth) registered to the colour image, so
depth pixel (u, v) and colour pixel (u, v) see the same point; both are in the colour camera's
(possibly distorted) pixels, and every pixel is undistorted before its ray is cast.

Two methods:

``"corners"`` (the paper's, section 2.5): for each corner, the depth is the mean over the N
frames of the valid (non-zero) depths in a small window around the corner pixel (``window_px``
= 1: the 3x3 pixels around the nearest pixel; the window straddles the code's edge, which is
fine on a flat board). The corner is back-projected along its undistorted ray at that z; the
axes follow equations 1-3 (x from c3 to c0, y from c3 to c2, z = x × y) and the translation
equation 4 (mean of the corners). x and y are not exactly orthogonal with noisy depth: the
matrix [x y z] is replaced by the nearest rotation (SVD, Frobenius norm), which spreads the
correction evenly over the axes instead of favouring x as Gram-Schmidt would.

``"plane"`` (default): the depth pixels inside the code's quadrilateral, shrunk towards its
centre by ``erode`` of the side (depth at the code's edges and across the quiet zone is where
misregistration and flying pixels hurt), from all N frames pooled (zeros ignored), are
back-projected and a plane is fitted by RANSAC (threshold from the expected structured-light
noise at that range, then least squares on the inliers). The plane's normal is then fused with
the normal that the code's own square gives by PnP (the module grid's corners when found), by
their covariances (:mod:`.qr_tilt`, issue 29: an uncorrected misregistration turns the plane
on oblique views, and the depth's noise tilts it on small, far or noisy codes, where PnP is
at its best; PnP is weakest square on, where the plane is best); ``normal="depth"`` keeps the
plane's own. The plane is turned about its samples' centroid to that normal, the four
sub-pixel corner rays are intersected with it, and the rotation is the best fit (Kabsch/SVD)
of the ideal square to the four 3D corners; the corners are coplanar, so its z is the fused
normal and its in-plane angle comes from the image corners. Why this is robust on a
Kinect-like sensor:

- disparity noise and 1/8 px quantisation average out over thousands of pixels, where the
  corners method sees nine;
- misregistration between depth and colour moves depth pixels along a flat board, which does
  not move the plane (the quad is eroded so no pixel near the board's edge is used), whereas
  the corners method samples the wrong spot;
- a depth scale bias (z read as (1 + b) z) scales the plane about the camera centre and with
  it the corners, which does not turn the plane; a misregistration on a tilted board moves the
  plane along the rays by (n_x du / fx + n_y dv / fy) / n_z of the range and also turns it,
  by about sin²(tilt) · shift / f (0.1° at 45° for 2 px at 570 px: :mod:`.qr_tilt`), which
  the tilt's fusion weighs by the shift's uncertainty (the sensor check's standard errors, or
  ``unchecked_shift_std_px``). With ``side_m`` (the
  printed side of the symbol) the image size of the code fixes the distance independently of
  both: the corners are rescaled along their rays so the mean measured side equals ``side_m``.
  The printed side is noisier than unbiased depth (about 0.02 px / side in px of the range,
  ~0.03 % = 0.3 mm at 1 m, against < 0.05 mm from the plane), so with ``scale="auto"``
  (default) the two distances are fused by their uncertainties (:func:`_fused_factor`): the
  depth's is its configured correction's (the sensor check's standard errors) or, when no
  check is configured, the typical systematic errors of an unchecked RGB-D sensor
  (``unchecked_scale_std`` 1 %, ``unchecked_shift_std_px`` 2 px; :func:`_unchecked_factor`).
  With a sensor check the printed distance comes from the code's module grid when it is found
  (free of the corners' edge bias and about half as noisy: on oblique and D435-like views the
  corners' side left 0.4-0.8 mm p95 where the grid leaves 0.17-0.32 mm), the corners' side
  (less ``corner_bias_px``) otherwise.
  Then the printed side carries the distance along the ray and the depth the orientation,
  unless the depth agrees with the side within AGREEMENT_SIGMAS of the side's noise, when its
  distance is kept exactly: a sensor without systematic errors loses nothing of its precision.
  Without a sensor check the code's image size is taken from its whole module grid
  (:mod:`.qr_grid`, when the decoder reports the symbol's version): the corners read the side
  ~0.03 px short with a ~0.02 px spread from view to view, which no number of frames averages
  out; the grid's hundreds of module edges give it to ~0.01 px without that bias. It is
  measured on the depth's plane mostly along the plane's tilt axis, where the plane's own
  normal error (~0.1°) does not stretch lengths (:func:`_grid_disagreement`).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Literal

import cv2
import numpy as np
from numpy.typing import NDArray

from geometry import CameraIntrinsics, fit_plane, orthonormalize

from .errors import BadImageError, DepthError, NotFoundError
from .expect import Expect
from .qr import gray_for_code, read_qr
from .qr_grid import grid_corners
from .qr_tilt import TiltFusion, corners_normal, fuse_normals, shift_normal_cov, tangent_basis

__all__ = [
    "QRPose",
    "QRPoseQuality",
    "qr_pose",
    "QR_CORNERS_QR",
    "UNCHECKED_SCALE_STD",
    "UNCHECKED_SHIFT_STD_PX",
]

UNCHECKED_SCALE_STD = 0.01
"""Depth scale error (relative std) assumed of a sensor whose check is not configured: RGB-D
cameras out of the box read 0.5-1 % off (issue 18; the sensor check measures the real one)."""
UNCHECKED_SHIFT_STD_PX = 2.0
"""Depth-to-colour misregistration (std per axis, pixels) assumed of an unchecked sensor: a
factory registration is typically off by 1-3 px."""

FloatArray = NDArray[np.float64]
Method = Literal["plane", "corners"]


def QR_CORNERS_QR(side_m: float) -> FloatArray:  # noqa: N802 - reads like a constant
    """The corners c0..c3 (4, 3) of a code of side ``side_m`` in its own QR frame."""
    h = side_m / 2
    return np.array([[h, -h, 0.0], [h, h, 0.0], [-h, h, 0.0], [-h, -h, 0.0]])


@dataclass(frozen=True)
class DepthCorrection:
    """A depth sensor's known systematic errors: its depth reads ``scale`` times the true z,
    and its pixel (u, v) saw the colour pixel (u - du, v - dv), ``shift_px`` = (du, dv)."""

    scale: float = 1.0
    shift_px: tuple[float, float] = (0.0, 0.0)


@dataclass(frozen=True)
class QRPoseQuality:
    """How much to trust a :class:`QRPose`.

    ``corner_depth_std_m`` (4,): spread (std) of the depth samples used at each corner
    (corners method), or of the plane residuals of the inliers near each corner (plane
    method), metres. ``valid_depth_fraction``: valid depth pixels / all pixels in the eroded
    quad over all frames. ``plane_rms_m``, ``inlier_fraction``: the plane fit (NaN for the
    corners method). ``orthogonality_rad``: |angle(x, y) - 90°| of eqs 1-2 before
    orthonormalisation. ``side_lengths_m`` (4,): |c0c1|, |c1c2|, |c2c3|, |c3c0| measured
    before any rescaling; ``side_m``: the printed side if given. ``scale``: the factor applied
    to the corners (1.0 without ``side_m``). ``frames``: depth frames used.

    Depth against the board (NaN without ``side_m``): ``depth_vs_side`` = (mean measured side
    / ``side_m``) - 1 after the configured depth correction, i.e. how much further the depth
    puts the board than its printed size does (relative; a depth scale error s adds s, a
    misregistration (du, dv) px adds ``shift_sensitivity`` · (du, dv), and corner noise
    ~0.03 %). ``shift_sensitivity`` (2,): that gain per pixel of misregistration, from the
    plane's tilt (n_x / (n_z fx), n_y / (n_z fy)); a view square to the camera has (0, 0),
    so one view cannot tell a shift from a scale: the sensor check fits several views.
    ``side_px``: the code's mean side in the image, pixels. ``depth_vs_grid``: the same
    disagreement from the code's module grid (see :func:`_grid_disagreement`; what the
    distance's fusion uses, checked or not), NaN when not measured (the corners were given,
    the grid was not found, or no ``side_m``).

    The plane method's tilt (:mod:`.qr_tilt`; NaN for the corners method or when the corners'
    normal was not available): ``plane_normal_std_rad`` and ``corners_normal_std_rad``, the
    larger principal std of the depth plane's normal (with the shift's uncertainty) and of the
    corners' (PnP); ``normal_turned_rad``, how far the fusion turned the plane's normal (0 when
    the two disagreed beyond qr_tilt.DISAGREEMENT_SIGMAS and the plane's was kept).
    """

    corner_depth_std_m: FloatArray
    valid_depth_fraction: float
    plane_rms_m: float
    inlier_fraction: float
    orthogonality_rad: float
    side_lengths_m: FloatArray
    side_m: float | None
    scale: float
    frames: int
    depth_vs_side: float = float("nan")
    side_px: float = float("nan")
    shift_sensitivity: FloatArray = dataclasses.field(default_factory=lambda: np.full(2, np.nan))
    depth_vs_grid: float = float("nan")
    plane_normal_std_rad: float = float("nan")
    corners_normal_std_rad: float = float("nan")
    normal_turned_rad: float = float("nan")


@dataclass(frozen=True)
class QRPose:
    """``camera_from_qr`` (4, 4); the code's ``text`` ("" when corners were given without
    ``expect``); ``corners_uv`` (4, 2) pixels and ``corners_camera`` (4, 3) metres, c0..c3;
    the ``method``; and the ``quality`` report."""

    camera_from_qr: FloatArray
    text: str
    corners_uv: FloatArray
    corners_camera: FloatArray
    method: str
    quality: QRPoseQuality


def _depth_stack(depth_frames: object, shape: tuple[int, int]) -> NDArray[np.uint16]:
    if isinstance(depth_frames, np.ndarray):
        stack = depth_frames[None] if depth_frames.ndim == 2 else depth_frames
    elif isinstance(depth_frames, Sequence) and len(depth_frames) > 0:
        frames = [np.asarray(f) for f in depth_frames]
        if any(f.shape != frames[0].shape for f in frames):
            raise BadImageError("depth frames differ in shape")
        stack = np.stack(frames)
    else:
        raise BadImageError("depth_frames must be an (H, W) or (N, H, W) array or a list of them")
    if stack.dtype != np.uint16:
        raise BadImageError(f"depth must be uint16 millimetres, got {stack.dtype}")
    if stack.ndim != 3 or stack.shape[0] < 1:
        raise BadImageError(f"depth must be (H, W) or (N, H, W), got {stack.shape}")
    if stack.shape[1:] != shape:
        raise BadImageError(
            f"depth {stack.shape[2]}x{stack.shape[1]} is not registered to the "
            f"{shape[1]}x{shape[0]} colour image and intrinsics"
        )
    return np.asarray(stack, np.uint16)


def _depth_m(z_mm: NDArray[np.uint16], levels: tuple[float, int] | None) -> FloatArray:
    """Depth in metres of valid (non-zero) millimetre values, undoing the mm rounding of a
    structured-light sensor when every value lies on its disparity table."""
    z = z_mm.astype(np.float64)
    if levels is not None and z.size:
        fb, steps = levels
        k = np.rint(fb * steps * 1000.0 / z)  # disparity in 1/steps px
        on_table = np.rint(fb * steps * 1000.0 / np.maximum(k, 1.0)) == z
        if float(on_table.mean()) >= 0.98:
            result: FloatArray = np.where(on_table, fb * steps / np.maximum(k, 1.0), z / 1000.0)
            return result
    return z / 1000.0


def _kabsch(model: FloatArray, measured: FloatArray) -> FloatArray:
    """Rotation R minimising sum |R model_i + t - measured_i|² (both (N, 3))."""
    a = model - model.mean(axis=0)
    b = measured - measured.mean(axis=0)
    u, _, vt = np.linalg.svd(b.T @ a)
    fix = np.diag([1.0, 1.0, float(np.sign(np.linalg.det(u @ vt)) or 1.0)])
    result: FloatArray = u @ fix @ vt
    return result


def _sides(c: FloatArray) -> FloatArray:
    result: FloatArray = np.linalg.norm(c - np.roll(c, -1, axis=0), axis=1)
    return result


def _orthogonality(c: FloatArray) -> float:
    x = c[0] - c[3]
    y = c[2] - c[3]
    cos = float(x @ y / (np.linalg.norm(x) * np.linalg.norm(y)))
    return abs(float(np.arccos(np.clip(cos, -1.0, 1.0))) - np.pi / 2)


def _check_corners(corners_uv: FloatArray, intr: CameraIntrinsics) -> None:
    area = 0.5 * abs(
        float(
            np.sum(
                corners_uv[:, 0] * np.roll(corners_uv[:, 1], -1)
                - np.roll(corners_uv[:, 0], -1) * corners_uv[:, 1]
            )
        )
    )
    if not np.all(np.isfinite(corners_uv)) or area < 25.0:
        raise DepthError(f"degenerate QR corners {corners_uv.tolist()} (area {area:.1f} px²)")
    inside = (
        (corners_uv[:, 0] >= -0.5)
        & (corners_uv[:, 0] <= intr.width - 0.5)
        & (corners_uv[:, 1] >= -0.5)
        & (corners_uv[:, 1] <= intr.height - 0.5)
    )
    if not inside.all():
        raise DepthError(f"QR corners c{np.flatnonzero(~inside).tolist()} lie outside the image")


def qr_pose(
    color: NDArray[np.generic] | None,
    depth_frames: NDArray[np.uint16] | Sequence[NDArray[np.uint16]],
    intrinsics: CameraIntrinsics,
    *,
    method: Method = "plane",
    corners: NDArray[np.float64] | None = None,
    expect: Expect = None,
    roi: Sequence[int] | None = None,
    side_m: float | None = None,
    scale: Literal["auto", "side", "depth"] = "auto",
    erode: float = 0.08,
    window_px: int = 1,
    ransac_threshold_m: float | None = None,
    min_valid_pixels: int = 50,
    disparity_levels: tuple[float, int] | None = (43.5, 8),
    depth_scale: float = 1.0,
    depth_shift_px: tuple[float, float] = (0.0, 0.0),
    depth_scale_std: float | None = None,
    depth_shift_std_px: tuple[float, float] = (0.0, 0.0),
    corner_bias_px: float | None = None,
    unchecked_scale_std: float = UNCHECKED_SCALE_STD,
    unchecked_shift_std_px: float = UNCHECKED_SHIFT_STD_PX,
    normal: Literal["fused", "depth"] = "fused",
) -> QRPose:
    """``camera_from_qr`` of the QR code in ``color`` (or at the given ``corners``).

    ``depth_frames``: one (H, W) or several ((N, H, W) or a list) uint16 mm depth images
    registered to ``color``. ``intrinsics``: the colour camera (with its distortion).
    ``corners`` (4, 2): c0..c3 in pixels (then ``color`` may be None); otherwise the code is
    read with :func:`read_qr` (``expect``, ``roi`` select it). ``side_m``: the printed side
    of the symbol; ``scale`` "side" rescales the corners along their rays so their mean side
    is ``side_m``, "depth" keeps the depth's distance, "auto" (default) fuses the two
    distances by their uncertainties (``depth_scale_std``, ``unchecked_scale_std``).
    ``erode``: fraction of the side removed around the quad's edge before the plane fit.
    ``window_px``: the corners method's half window. ``ransac_threshold_m``: default from
    the sensor noise at that range.
    ``disparity_levels`` ``(fb_px_m, steps)``: a structured-light sensor reports z = fb / d
    with d quantised to 1/steps px, rounded to mm; when (and only when) at least 98 % of the
    depth values lie exactly on that table, each is snapped back to its level's exact z,
    which removes the ±0.5 mm rounding that does not average out over frames (it biases the
    plane's tilt by up to ~0.2°). None turns this off.
    ``depth_scale`` and ``depth_shift_px`` correct a sensor whose depth reads ``depth_scale``
    times the true z and whose depth pixel (u, v) sees the colour pixel (u - du, v - dv)
    (the values the sensor check measures, :mod:`.depth_registration`); the defaults assume
    a perfect sensor. ``depth_scale_std`` and ``depth_shift_std_px``: their uncertainties (the
    check's standard errors); given with ``side_m`` and ``scale="auto"``, the distance is the
    fusion of the corrected depth's and the printed side's by their variances (see
    :func:`_fused_factor`). ``corner_bias_px``: how much too long the corner detector reads
    the code's image side on this camera (negative: too short), removed from the side before
    the fusion (None: not measured, so the side's uncertainty includes
    UNMEASURED_CORNER_BIAS_STD_PX). ``unchecked_scale_std`` (relative) and
    ``unchecked_shift_std_px`` (pixels, each axis): the systematic errors assumed of a sensor
    whose check is not configured (no ``depth_scale``, ``depth_shift_px`` or
    ``depth_scale_std``), typical of an RGB-D camera out
    of the box (scale 0.5-1 %, registration a few pixels); 0 and 0 keep the depth's distance
    as it is. See :func:`_unchecked_factor`. The shift's std also weighs the depth plane's
    tilt against the corners' (an uncorrected shift turns the plane).
    ``normal`` (plane method): "fused" (default) fuses the depth plane's normal with the
    corners' (PnP) by their covariances, "depth" keeps the plane's (see :mod:`.qr_tilt`).

    Raises NotFoundError (no code), DepthError (a corner without depth, too few depth pixels,
    degenerate geometry), BadImageError (bad depth frames).
    """
    if method not in ("plane", "corners"):
        raise ValueError(f"method must be 'plane' or 'corners', got {method!r}")
    if normal not in ("fused", "depth"):
        raise ValueError(f"normal must be 'fused' or 'depth', got {normal!r}")
    if side_m is not None and not side_m > 0:
        raise ValueError(f"side_m must be positive, got {side_m}")
    if scale not in ("auto", "side", "depth"):
        raise ValueError(f"scale must be 'auto', 'side' or 'depth', got {scale!r}")
    if scale == "side" and side_m is None:
        raise ValueError("scale='side' needs side_m")
    if not depth_scale > 0:
        raise ValueError(f"depth_scale must be positive, got {depth_scale}")
    if not (unchecked_scale_std >= 0 and np.isfinite(unchecked_scale_std)):
        raise ValueError(f"unchecked_scale_std must be >= 0, got {unchecked_scale_std}")
    if not (unchecked_shift_std_px >= 0 and np.isfinite(unchecked_shift_std_px)):
        raise ValueError(f"unchecked_shift_std_px must be >= 0, got {unchecked_shift_std_px}")
    shape = (intrinsics.height, intrinsics.width)
    if color is not None and np.asarray(color).shape[:2] != shape:
        # Before the depth: a depth frame of the colour image's size is registered to it; the
        # two differ from the camera's intrinsics, which is what must be said.
        got = np.asarray(color).shape[:2]
        raise BadImageError(
            f"the colour image is {got[1]}x{got[0]}, the camera's intrinsics are for "
            f"{shape[1]}x{shape[0]}: send the camera's full frames (a crop or another "
            "resolution needs intrinsics of its own)"
        )
    depth = _depth_stack(depth_frames, shape)
    correction = DepthCorrection(
        float(depth_scale), (float(depth_shift_px[0]), float(depth_shift_px[1]))
    )

    if corners is None:
        if color is None:
            raise NotFoundError("neither a colour image nor corners given")
        code = read_qr(color, roi=roi, expect=expect)[0]
        corners_uv, text, modules = code.corners, code.text, code.modules
    else:
        corners_uv = np.asarray(corners, np.float64)
        if corners_uv.shape != (4, 2):
            raise ValueError(f"corners must have shape (4, 2), got {corners_uv.shape}")
        text = expect if isinstance(expect, str) else ""
        modules = None  # corners from elsewhere: the module grid is not looked for
    _check_corners(corners_uv, intrinsics)

    checked = depth_scale_std is not None or correction != DepthCorrection()
    grid_uv: FloatArray | None = None
    tilt: TiltFusion | None = None
    if method == "corners":
        corners_cam, spread, valid_fraction = _corners_method(
            corners_uv, depth, intrinsics, window_px, disparity_levels, correction
        )
        rms = inlier_fraction = float("nan")
    else:
        plane = _plane_method(
            corners_uv,
            depth,
            intrinsics,
            erode,
            ransac_threshold_m,
            min_valid_pixels,
            disparity_levels,
            correction,
        )
        corners_cam, spread, valid_fraction = plane.corners_cam, plane.spread, plane.valid_fraction
        rms, inlier_fraction = plane.rms, plane.inlier_fraction
        if color is not None and modules is not None:
            grid_uv = _grid(color, corners_uv, modules, intrinsics)
        if normal == "fused":
            if checked:
                # the check's standard errors (a correction given without them is exact); a
                # shift the check could not determine is as uncertain as an unchecked one
                shift_std = tuple(
                    float(x) if np.isfinite(x) else unchecked_shift_std_px
                    for x in depth_shift_std_px
                )
            else:
                shift_std = (unchecked_shift_std_px, unchecked_shift_std_px)
            tilt = _fused_tilt(
                plane,
                corners_uv if grid_uv is None else grid_uv,
                grid_uv is not None,
                intrinsics,
                side_m,
                (shift_std[0], shift_std[1]),
            )
            turned = (
                None
                if tilt is None or not tilt.used
                else _onto_plane(plane.centroid, corners_uv, tilt.normal, intrinsics)
            )
            if turned is not None:
                corners_cam = turned

    sides = _sides(corners_cam)
    if not np.all(sides > 1e-4):
        raise DepthError(f"degenerate QR geometry: side lengths {sides.tolist()} m")
    orthogonality = _orthogonality(corners_cam)
    factor = 1.0
    depth_vs_grid = float("nan")
    side_px = float(np.mean(_sides(corners_uv)))
    sensitivity = _shift_sensitivity(corners_cam, intrinsics)
    if side_m is not None and scale == "auto":
        disagreement = float(sides.mean()) / side_m - 1.0
        grid = (
            None
            if grid_uv is None or modules is None
            else _grid_disagreement(
                grid_uv,
                corners_cam,
                modules,
                intrinsics,
                side_m,
                side_px,
                tilt.fused_std_rad if tilt is not None and tilt.used else PLANE_NORMAL_STD_RAD,
            )
        )
        if checked and grid is not None:
            # the module grid's size: free of the corners' edge bias and ~2x less noisy
            depth_vs_grid, var_grid = grid
            factor = _fused_factor(
                depth_vs_grid,
                side_px,
                sensitivity,
                depth_scale_std or 0.0,
                depth_shift_std_px,
                0.0,
                side_noise_px=float(np.sqrt(var_grid)) * side_px,
            )
        elif checked:
            # a correction without its standard errors is taken as exact
            factor = _fused_factor(
                disagreement,
                side_px,
                sensitivity,
                depth_scale_std or 0.0,
                depth_shift_std_px,
                corner_bias_px or 0.0,
            )
        else:
            if grid is not None:
                depth_vs_grid, var_grid = grid
                factor = _unchecked_factor(
                    depth_vs_grid,
                    side_px,
                    sensitivity,
                    unchecked_scale_std,
                    unchecked_shift_std_px,
                    0.0,
                    side_noise_px=float(np.sqrt(var_grid)) * side_px,
                )
            else:
                factor = _unchecked_factor(
                    disagreement,
                    side_px,
                    sensitivity,
                    unchecked_scale_std,
                    unchecked_shift_std_px,
                    corner_bias_px,
                )
        corners_cam = corners_cam * factor  # along the rays through the camera centre
    elif side_m is not None and scale == "side":
        factor = side_m / float(sides.mean())
        corners_cam = corners_cam * factor

    if method == "corners":
        x = corners_cam[0] - corners_cam[3]
        y = corners_cam[2] - corners_cam[3]
        x /= np.linalg.norm(x)
        y /= np.linalg.norm(y)
        z = np.cross(x, y)
        if np.linalg.norm(z) < 1e-6:
            raise DepthError("degenerate QR geometry: x and y axes are parallel")
        rotation = orthonormalize(np.column_stack([x, y, z / np.linalg.norm(z)]))
    else:
        model = QR_CORNERS_QR(side_m if side_m is not None else float(sides.mean()))
        rotation = _kabsch(model, corners_cam)
    depth_vs_side = float("nan") if side_m is None else float(sides.mean()) / side_m - 1.0
    camera_from_qr = np.eye(4)
    camera_from_qr[:3, :3] = rotation
    camera_from_qr[:3, 3] = corners_cam.mean(axis=0)
    quality = QRPoseQuality(
        corner_depth_std_m=spread,
        valid_depth_fraction=valid_fraction,
        plane_rms_m=rms,
        inlier_fraction=inlier_fraction,
        orthogonality_rad=orthogonality,
        side_lengths_m=sides,
        side_m=side_m,
        scale=factor,
        frames=int(depth.shape[0]),
        depth_vs_side=depth_vs_side,
        side_px=side_px,
        shift_sensitivity=sensitivity,
        depth_vs_grid=depth_vs_grid,
        plane_normal_std_rad=float("nan") if tilt is None else tilt.plane_std_rad,
        corners_normal_std_rad=float("nan") if tilt is None else tilt.corners_std_rad,
        normal_turned_rad=float("nan") if tilt is None else tilt.turned_rad,
    )
    return QRPose(camera_from_qr, text, corners_uv.copy(), corners_cam, method, quality)


# The noise of the code's mean image side from the sub-pixel corner detector (read_qr), std in
# pixels, measured against the simulated camera's truth at 0.7-1.3 m. The detector's *bias* on
# the side depends on the camera's blur and on the detector itself, so it is configured per
# camera (``corner_bias_px``, measured against a known reference), not assumed here: on the
# simulated Xtion-like camera about -0.03 px (bench/calibration.py measures it each run against
# the renderer's truth; -0.07 px was an earlier detector's, and configuring it today
# over-corrects the depth scale by ~0.04 %).
SIDE_NOISE_PX = 0.024
UNMEASURED_CORNER_BIAS_STD_PX = 0.05
"""The uncertainty of the corner detector's bias on the side when ``corner_bias_px`` is not
configured: the simulated camera's was -0.07 px with an earlier detector and is -0.03 px with
today's, so a camera nobody measured is assumed within about +/-0.05 px (1 std)."""


GRID_AXIS_NOISE_PX = 0.010
"""The error of the code's size measured by its module grid (:mod:`.qr_grid`) in one
direction on the code's plane, std in pixels of the side it implies: 0.009-0.0105 px (mean
-0.002 to -0.004 px: no bias worth configuring) against the simulated camera's truth on two
sets of 40 views at 0.6-1.5 m that the bench does not evaluate (bench/calibration.py's view
generator, seeds 53 and 59). The corners' side has 0.018-0.020 px around a -0.033 px bias."""
PLANE_COV_FACTOR = 1.0
"""Calibration of the plane's normal covariance (:func:`_plane_method`, frames counted as one):
against the simulation's truth (15 views in each of ten scene families: the bench's, oblique,
far, small code, near the border, a plate off the wall, D435- and D405-like stereo, distortion,
holes) the normal's error is 0.5-1.3 times its stated std (median 0.86), so no factor; the
D405-like camera at 0.2-0.45 m reads 3.5 times (its millimetre depth is coarse against its
noise there), where the tilt test of :func:`.qr_tilt.fuse_normals` may keep the plane."""
GRID_CORNER_NOISE_PX = 0.02
"""The module grid's corners' noise (std per coordinate, px) for the corners' normal: PnP's
normal error on the same views was 0.84 times its std at 0.015 px (median; 0.7-2.5 by family)."""
CORNER_NOISE_PX = 0.06
"""The detected corners' noise (std per coordinate, px) for the corners' normal, when the grid
is not found: 1.8 times PnP's std at 0.03 px on the same views (median; 1.5-3.7 by family)."""
PLANE_NORMAL_STD_RAD = float(np.radians(0.1))
"""The depth plane's normal error (std) at 0.6-1.5 m over 5 frames: the plane method's
rotation p95 is 0.11-0.15° on the bench (docs/BENCHMARKS.md section 4)."""

AGREEMENT_SIGMAS = 3.0
"""Without a sensor check, the depth's distance is kept while it disagrees with the printed
side (the module grid's size) by at most this many of the side's stds (:func:`_unchecked_factor`).
Measured on a sensor without systematic errors (the simulated Xtion-like camera, 0.6-1.5 m,
1-5 depth frames): the disagreement is 0.74-0.95 of its stated std, 4 of 532 views beyond
2.5 stds, 1 beyond 3 (3.3); on (2, 1) px with +0.5 % or +-1 % scale it is 27-196 stds."""
AGREEMENT_RAMP_SIGMAS = 1.0
"""Over this many stds beyond AGREEMENT_SIGMAS the test's verdict goes from 'agrees' to
'disagrees', so that the distance does not jump at the test's edge."""


def _grid(
    color: NDArray[np.generic], corners_uv: FloatArray, modules: int, intr: CameraIntrinsics
) -> FloatArray | None:
    """The code's outer corners from its module grid (:func:`.qr_grid.grid_corners`, through
    the lens's distortion), None when the grid is not found."""
    try:
        return grid_corners(gray_for_code(color), corners_uv, modules, intrinsics=intr)
    except (BadImageError, ValueError):
        return None


def _fused_tilt(
    plane: _Plane,
    corners_uv: FloatArray,
    from_grid: bool,
    intr: CameraIntrinsics,
    side_m: float | None,
    shift_std_px: tuple[float, float],
) -> TiltFusion | None:
    """The plane's normal fused with the corners' (see :mod:`.qr_tilt`): the plane's covariance
    is its fit's (``plane.normal_cov``) plus what a depth-to-colour shift of ``shift_std_px``
    turns it by; the corners' is PnP's at GRID_CORNER_NOISE_PX (``from_grid``: the module
    grid's corners) or CORNER_NOISE_PX. None when either is not available."""
    if not np.all(np.isfinite(plane.normal_cov)):
        return None
    basis = tangent_basis(plane.normal)
    plane_cov = plane.normal_cov + shift_normal_cov(
        plane.normal, basis, intr.fx, intr.fy, shift_std_px
    )
    found = corners_normal(
        intr.undistort_pixels(corners_uv),
        side_m if side_m is not None else 1.0,  # the rotation does not depend on the size
        intr.fx,
        intr.fy,
        GRID_CORNER_NOISE_PX if from_grid else CORNER_NOISE_PX,
        plane.normal,
    )
    if found is None:
        return None
    return fuse_normals(plane.normal, plane_cov, found[0], found[1])


def _onto_plane(
    centroid: FloatArray, corners_uv: FloatArray, normal: FloatArray, intr: CameraIntrinsics
) -> FloatArray | None:
    """The corner rays met with the plane of ``normal`` through the depth samples' ``centroid``
    (the depth's plane turned about the point where it is best determined; only the tilt
    changes). None when the plane is seen edge-on or behind the camera."""
    rays = intr.pixel_rays(corners_uv)
    denom = rays @ normal
    if np.any(np.abs(denom) < 1e-3):
        return None
    s = float(normal @ centroid) / denom
    if np.any(s <= 0):
        return None
    result: FloatArray = rays * s[:, None]
    return result


def _grid_disagreement(
    grid_uv: FloatArray,
    corners_cam: FloatArray,
    modules: int,
    intr: CameraIntrinsics,
    side_m: float,
    side_px: float,
    normal_std_rad: float = PLANE_NORMAL_STD_RAD,
) -> tuple[float, float] | None:
    """How much further the depth puts the code than its module grid's image size does
    (relative, like ``depth_vs_side``), and that figure's variance (relative²).

    The grid's corners (:func:`.qr_grid.grid_corners`) are cast onto the plane of
    ``corners_cam`` (camera frame, m), and the code's module length on that plane is measured
    in two directions: along the plane's tilt axis (the in-plane direction square to the
    camera's ray through the code) and across it. Why two: the plane's normal is off by ~0.1°
    (depth noise, PLANE_NORMAL_STD_RAD), and a normal error d stretches lengths across the tilt
    axis by tan(tilt) d (0.07 % at 20° and 0.18°: 1 mm at 1.4 m) but not along it; each
    direction has the grid's own noise (GRID_AXIS_NOISE_PX / ``side_px``). The two are weighed
    by their variances. ``grid_uv``: the grid's corners (:func:`_grid`); ``normal_std_rad``: the
    normal's std (the tilt fusion's, :mod:`.qr_tilt`, when it was fused: with the corners' the
    normal is better known than the plane's 0.1°, and the direction across the tilt axis
    counts for more)."""
    normal = np.cross(corners_cam[2] - corners_cam[0], corners_cam[3] - corners_cam[1])
    normal /= np.linalg.norm(normal)
    centre = corners_cam.mean(axis=0)
    rays = intr.pixel_rays(grid_uv)
    denom = rays @ normal
    if np.any(np.abs(denom) < 1e-12):
        return None
    points = rays * (float(centre @ normal) / denom)[:, None]
    # the affine map (3, 2) per module from the code's module coordinates (x right, y down on
    # the print; the corners at 0 and N) to the plane, least squares over the four corners
    model = np.array([[0.0, 0.0], [1.0, 0.0], [1.0, 1.0], [0.0, 1.0]]) * modules
    model -= model.mean(axis=0)
    per_module = (points - points.mean(axis=0)).T @ np.linalg.pinv(model.T)
    ray = centre / np.linalg.norm(centre)
    along = np.cross(normal, ray)
    sin_tilt = float(np.linalg.norm(along))
    if sin_tilt < 1e-6:  # square to the camera: any in-plane direction is a tilt axis
        along = per_module[:, 0] - (per_module[:, 0] @ normal) * normal
        sin_tilt = 0.0
    along /= np.linalg.norm(along)
    across = np.cross(normal, along)
    expected = side_m / modules
    r_along = float(np.linalg.norm(along @ per_module)) / expected - 1.0
    r_across = float(np.linalg.norm(across @ per_module)) / expected - 1.0
    var_grid = (GRID_AXIS_NOISE_PX / side_px) ** 2
    tan_tilt = sin_tilt / max(float(np.sqrt(1.0 - sin_tilt**2)), 1e-6)
    w_along = 1.0 / var_grid
    w_across = 1.0 / (var_grid + (tan_tilt * normal_std_rad) ** 2)
    r = (w_along * r_along + w_across * r_across) / (w_along + w_across)
    return r, 1.0 / (w_along + w_across)


def _shift_sensitivity(corners_cam: FloatArray, intr: CameraIntrinsics) -> FloatArray:
    """d(depth_vs_side) / d(du, dv) per pixel: (n_x / (n_z fx), n_y / (n_z fy)) of the plane
    through the corners (the sign of n cancels)."""
    n = np.cross(corners_cam[2] - corners_cam[0], corners_cam[3] - corners_cam[1])
    result: FloatArray = np.array([n[0] / (n[2] * intr.fx), n[1] / (n[2] * intr.fy)])
    return result


def _fused_factor(
    depth_vs_side: float,
    side_px: float,
    sensitivity: FloatArray,
    scale_std: float,
    shift_std_px: tuple[float, float],
    corner_bias_px: float,
    *,
    side_noise_px: float = SIDE_NOISE_PX,
) -> float:
    """The factor on the corrected depth's corners that fuses two distances by their variances:
    the depth's (relative variance scale_std² + (g · shift_std)², the correction's own
    uncertainty) and the printed side's (SIDE_NOISE_PX / side_px, after removing the
    detector's ``corner_bias_px``). The fused distance is the depth's times 1 / (1 + w r), r the
    disagreement, w = var_depth / (var_depth + var_side)."""
    r = (1.0 + depth_vs_side) / (1.0 + corner_bias_px / side_px) - 1.0
    var_depth = (
        scale_std**2
        + float((sensitivity[0] * shift_std_px[0]) ** 2)
        + float((sensitivity[1] * shift_std_px[1]) ** 2)
    )
    var_side = (side_noise_px / side_px) ** 2
    if not np.isfinite(var_depth) or var_depth + var_side <= 0:
        return 1.0
    w = var_depth / (var_depth + var_side)
    return 1.0 / (1.0 + w * r)


def _unchecked_factor(
    depth_vs_side: float,
    side_px: float,
    sensitivity: FloatArray,
    scale_std: float,
    shift_std_px: float,
    corner_bias_px: float | None,
    *,
    side_noise_px: float = SIDE_NOISE_PX,
) -> float:
    """The factor on the uncorrected depth's corners when no sensor check is configured.

    The depth's systematic error is unknown: either the sensor has none worth naming (its
    distance is then far more precise than the printed side's) or it has the typical error
    of an unchecked RGB-D camera, relative std sqrt(scale_std² + (g · shift_std_px)²) with g
    the view's shift sensitivity (per pixel). The disagreement r with the printed side
    (relative std SIDE_NOISE_PX / side_px, or the module grid's ``side_noise_px``; with
    UNMEASURED_CORNER_BIAS_STD_PX when ``corner_bias_px`` is None) decides, in two steps:

    - an agreement test: while |r| is within AGREEMENT_SIGMAS of the side's std, the depth
      agrees with the side as well as a sensor without systematic errors does, and its
      distance is kept exactly (it is ~5-10 times more precise than the side's);
    - beyond it, the two hypotheses, equally likely beforehand, are weighed by how well each
      explains r, and the depth's error is their posterior mean (the side's distance when the
      depth evidently disagrees). The test's verdict is ramped in over AGREEMENT_RAMP_SIGMAS,
      so the distance does not jump at the test's edge.

    Why the test before the posterior: the posterior alone already moved views whose side
    disagreed by 2-3 stds (weight 0.27 at 2.56 stds), which a perfect sensor shows on ~1 % of
    its views (the side's own tail), and then the side's error replaced the depth's: on the
    bench's perfect sensor one view went 0.057 -> 0.138 mm and the p95 0.084 -> 0.096 mm. A
    sensor whose systematic error on a view is within the test keeps about AGREEMENT_SIGMAS
    side stds of it at most (with the module grid 0.02-0.045 %, 0.1-0.65 mm at 0.6-1.5 m,
    against ~1.6 stds with the posterior alone); a typical unchecked sensor is 27-196 stds
    off and is unaffected.
    """
    if corner_bias_px is None:
        r = depth_vs_side
        var_side = (SIDE_NOISE_PX**2 + UNMEASURED_CORNER_BIAS_STD_PX**2) / side_px**2
    else:
        r = (1.0 + depth_vs_side) / (1.0 + corner_bias_px / side_px) - 1.0
        var_side = (side_noise_px / side_px) ** 2
    var_sys = scale_std**2 + float(np.sum((sensitivity * shift_std_px) ** 2))
    if not (np.isfinite(r) and np.isfinite(var_sys)) or var_sys <= 0 or var_side <= 0:
        return 1.0
    # the agreement test: 0 while the depth agrees with the side, 1 from a clear disagreement
    sigmas = abs(r) / float(np.sqrt(var_side))
    disagrees = min(max((sigmas - AGREEMENT_SIGMAS) / AGREEMENT_RAMP_SIGMAS, 0.0), 1.0)
    if disagrees == 0.0:
        return 1.0
    var_both = var_sys + var_side
    # log-likelihood ratio of "no systematic error" to "a typical one" given r
    log_ratio = 0.5 * r * r * (1.0 / var_both - 1.0 / var_side) + 0.5 * np.log(var_both / var_side)
    p_sys = 1.0 / (1.0 + float(np.exp(min(log_ratio, 700.0))))
    error = disagrees * p_sys * var_sys / var_both * r
    return 1.0 / (1.0 + error)


def _corners_method(
    corners_uv: FloatArray,
    depth: NDArray[np.uint16],
    intr: CameraIntrinsics,
    window: int,
    levels: tuple[float, int] | None,
    correction: DepthCorrection,
) -> tuple[FloatArray, FloatArray, float]:
    h, w = depth.shape[1:]
    z = np.zeros(4)
    spread = np.zeros(4)
    valid_total = 0
    count_total = 0
    du, dv = correction.shift_px
    for i, (u, v) in enumerate(corners_uv):
        # the depth pixel that saw this colour pixel
        cu, cv = int(np.rint(u + du)), int(np.rint(v + dv))
        patch = depth[
            :,
            max(cv - window, 0) : min(cv + window + 1, h),
            max(cu - window, 0) : min(cu + window + 1, w),
        ]
        samples = _depth_m(patch[patch > 0], levels) / correction.scale
        valid_total += samples.size
        count_total += patch.size
        if samples.size == 0:
            raise DepthError(
                f"no valid depth at QR corner c{i} ({u:.1f}, {v:.1f}) in {depth.shape[0]} frames"
            )
        z[i] = samples.mean()
        spread[i] = samples.std()
    corners_cam = intr.backproject(corners_uv, z)
    return corners_cam, spread, valid_total / max(count_total, 1)


@dataclass(frozen=True)
class _Plane:
    """The plane method's fit: the corners on the plane (4, 3), the residual spread near each
    corner (4,), the valid depth fraction, the RMS residual (m), the inlier fraction, the unit
    normal (3, towards the camera) and its covariance (2, 2; rad², in
    ``tangent_basis(normal)``) from the depth's noise alone, and the inliers' centroid (3,),
    the point the plane is best determined at (its tilt errors turn it about that point)."""

    corners_cam: FloatArray
    spread: FloatArray
    valid_fraction: float
    rms: float
    inlier_fraction: float
    normal: FloatArray
    normal_cov: FloatArray
    centroid: FloatArray


def _plane_method(
    corners_uv: FloatArray,
    depth: NDArray[np.uint16],
    intr: CameraIntrinsics,
    erode: float,
    threshold: float | None,
    min_valid: int,
    levels: tuple[float, int] | None,
    correction: DepthCorrection,
    max_points: int = 25000,
) -> _Plane:
    n_frames, h, w = depth.shape
    centre = corners_uv.mean(axis=0)
    quad = centre + (1.0 - 2.0 * erode) * (corners_uv - centre)
    u0 = int(np.clip(np.floor(quad[:, 0].min()), 0, w - 1))
    u1 = int(np.clip(np.ceil(quad[:, 0].max()), 0, w - 1))
    v0 = int(np.clip(np.floor(quad[:, 1].min()), 0, h - 1))
    v1 = int(np.clip(np.ceil(quad[:, 1].max()), 0, h - 1))
    mask = np.zeros((v1 - v0 + 1, u1 - u0 + 1), np.uint8)
    shift = 4  # fillPoly's fixed-point sub-pixel bits
    pts = np.rint((quad - [u0, v0]) * (1 << shift)).astype(np.int32)
    cv2.fillPoly(mask, [pts], 1, lineType=cv2.LINE_8, shift=shift)
    vv, uu = np.nonzero(mask)
    if vv.size == 0:
        raise DepthError("the QR code is too small for a plane fit")
    # at most ~max_points pooled samples: a regular pixel grid beyond that (a large code at
    # close range has plenty; the plane's precision then exceeds the corners' anyway)
    stride = int(np.ceil(np.sqrt(vv.size * n_frames / max_points)))
    if stride > 1:
        keep = ((vv + v0) % stride == 0) & ((uu + u0) % stride == 0)
        vv, uu = vv[keep], uu[keep]
    uv = np.column_stack([uu + u0, vv + v0]).astype(np.float64)
    # depth pixel (u, v) measured the colour pixel (u - du, v - dv): cast that pixel's ray
    xy = intr.undistort_pixels(uv - np.asarray(correction.shift_px))  # shared by all frames
    zmm = depth[:, vv + v0, uu + u0]  # (N, P)
    valid = zmm > 0
    valid_fraction = float(valid.mean())
    n_valid = int(valid.sum())
    if n_valid < min_valid:
        raise DepthError(
            f"too few valid depth pixels in the QR code: {n_valid} in {n_frames} frames "
            f"(need {min_valid})"
        )
    z = _depth_m(zmm[valid], levels) / correction.scale
    pix = np.nonzero(valid)[1]
    points = np.column_stack([xy[pix, 0] * z, xy[pix, 1] * z, z])
    z_med = float(z.mean())
    if threshold is None:
        # structured light: sigma_z ~ z² sigma_d / fb (1.4 mm at 1 m) plus 1/8 px steps
        threshold = 0.002 + 0.005 * z_med * z_med
    rng = np.random.default_rng(0)
    sample = points if len(points) <= 1500 else points[rng.choice(len(points), 1500, replace=False)]
    try:
        rough = fit_plane(sample, ransac_threshold_m=threshold, ransac_iterations=60, rng=rng)
    except ValueError as exc:
        raise DepthError(f"no plane through the QR code's depth: {exc}") from exc
    inliers = np.abs(points @ rough.normal + rough.d) <= threshold
    if int(inliers.sum()) < max(3, min_valid // 2):
        raise DepthError(f"no plane through the QR code's depth ({int(inliers.sum())} inliers)")
    # least squares on all inliers: smallest eigenvector of the 3x3 scatter matrix
    inl = points[inliers]
    centroid = inl.mean(axis=0)
    centred = inl - centroid
    _, vecs = np.linalg.eigh(centred.T @ centred)
    normal = vecs[:, 0]
    if normal @ centroid > 0:
        normal = -normal  # towards the camera
    d = -float(normal @ centroid)
    residual = centred @ normal
    rays = intr.pixel_rays(corners_uv)
    denom = rays @ normal
    if np.any(np.abs(denom) < 1e-3):
        raise DepthError("degenerate QR geometry: the code's plane is seen edge-on")
    s = -d / denom
    if np.any(s <= 0):
        raise DepthError("degenerate QR geometry: the plane lies behind the camera")
    corners_cam: FloatArray = rays * s[:, None]
    # spread near each corner: residuals of inlier points within a quarter side of it
    in_uv = uv[pix[inliers]]
    side_px = float(np.mean(np.linalg.norm(quad - np.roll(quad, -1, axis=0), axis=1)))
    spread = np.full(4, np.nan)
    for i in range(4):
        near = np.sum((in_uv - quad[i]) ** 2, axis=1) < (0.25 * side_px) ** 2
        if near.any():
            spread[i] = float(residual[near].std())
    # the normal's covariance in tangent angles: residual variance over the samples' spread on
    # the plane, with the frames counted as one (the simulated sensor's noise, like a real
    # one's, repeats in part from frame to frame: the pooled count put the normal's std 2-3
    # times too low against the truth)
    basis = tangent_basis(normal)
    spread_on_plane = centred @ basis.T
    variance = float(np.mean(residual**2))
    try:
        normal_cov = (
            PLANE_COV_FACTOR
            * n_frames
            * variance
            * np.linalg.inv(spread_on_plane.T @ spread_on_plane)
        )
    except np.linalg.LinAlgError:
        normal_cov = np.full((2, 2), np.nan)
    return _Plane(
        corners_cam,
        spread,
        valid_fraction,
        float(np.sqrt(variance)),
        float(inliers.mean()),
        normal,
        np.asarray(normal_cov, np.float64),
        centroid,
    )
