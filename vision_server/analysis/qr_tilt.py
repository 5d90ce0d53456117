"""The QR code's tilt (its plane's normal) from two independent measurements, fused by their
covariances: the depth's plane and the code's printed square seen in the image.

Why (issue 29 part 4): on views that the bench's did not cover, with depth misregistered by
(2, 1) px and scaled by +0.5 %, the plane method's rotation p95 reached 0.23°. Two mechanisms,
measured on the simulated cell (bench/calibration.py, the hard scene table; 20 views of 5
frames per kind of scene, the depth's tilt alone: 0.35° p95 on a D435-like 1280x720 camera,
0.16° unchecked on views 30-60° off square against 0.10° checked, 0.43° on a 6 cm code, 1.0°
at 1.5-2.5 m, 0.55° on a D405-like camera at 0.2-0.45 m; near the image border, with 10 %
holes, through a distorted lens or on a plate standing off the wall no worse than the bench's
0.09-0.15°. Misregistered depth bleeding across the plate's edge played no part: the quad is
eroded by 8 % of the side, several pixels more than the shift, inside a quiet zone):

- a misregistration that is not corrected *turns* the depth's plane. A plane's inverse depth is
  1/z = a x + b y + c in normalised image coordinates; depth shifted by (du, dv) px keeps a and
  b and changes c by -(a du / fx + b dv / fy), which turns the normal (a, b, c) towards or away
  from the optical axis by about sin²(tilt) · (shift along the tilt) / f: 0.03° at 20°, 0.1° at
  45°, 0.17° at 60° for 2.2 px at f = 570 px. The sensor check removes it; the unchecked path
  (no correction configured) keeps it, and it is largest on oblique views;
- the depth's noise: the plane's normal error grows with the noise (z² / (f b) for stereo and
  structured light) and shrinks with the code's size in pixels, so small or far codes and noisy
  sensors (a D435- or D405-like stereo camera at the edge of its range) reach 0.3-0.8° p95 on
  either path, misregistered or not (the same with a sensor without systematic errors).

The code's square is the other measurement of the same normal: the four outer corners (from the
module grid when the symbol's version is known, :mod:`.qr_grid`, ~0.01 px) and the printed
square give the pose by PnP (IPPE). It is weakest where the plane is strongest: square to the
camera, the perspective of a small square hardly changes with the tilt (PnP p95 0.4-2.5° on
frontal views), but at 30-60° off square it gives the normal to ~0.02°, where an uncorrected
misregistration turns the plane most. Neither alone meets the goal on every view, so the normal
is the covariance-weighted mean of the two (each linearised about the plane's normal, two
tangent angles): the plane's covariance is its least-squares one (residual variance over the
spread of the samples, the frames counted as one because much of a depth sensor's noise
repeats from frame to frame) plus what the depth-to-colour shift's uncertainty turns it by
(the unchecked sensor's assumed 2 px, or the sensor check's standard errors); the corners'
covariance is PnP's, from the Jacobian of the corners' reprojection at the corner noise. When
the two disagree beyond DISAGREEMENT_SIGMAS of their combined covariance (a corner found in the
wrong place, a plane through something else) the depth's normal is kept.

Why not the alternatives the issue named: eroding the sampling region or weighting the plane's
samples robustly does nothing against either mechanism (the whole plane turns, and the noise is
not in outliers); PnP's rotation alone is 0.4-2.5° p95 on frontal views. Measured after the
fusion (same views): 0.13° on the D435-like camera, 0.10° on the oblique views, 0.26° on the
6 cm code, 0.39° at 1.5-2.5 m; the D405-like camera's plane is 3.5 times further off than its
covariance says (millimetre depth, coarse against its noise at 0.3 m), so the disagreement
test mostly keeps it there (0.5° p95): not solved.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
from numpy.typing import NDArray

__all__ = ["TiltFusion", "corners_normal", "fuse_normals", "shift_normal_cov", "tangent_basis"]

FloatArray = NDArray[np.float64]

DISAGREEMENT_SIGMAS = 5.0
"""Beyond this many stds of the combined covariance the corners' normal is not used."""


def tangent_basis(normal: FloatArray) -> FloatArray:
    """Two unit vectors (2, 3) square to ``normal`` and to each other."""
    n = normal / np.linalg.norm(normal)
    helper = np.array([1.0, 0.0, 0.0]) if abs(n[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    e1 = np.cross(n, helper)
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(n, e1)
    result: FloatArray = np.vstack([e1, e2])
    return result


def shift_normal_cov(
    normal: FloatArray,
    basis: FloatArray,
    fx: float,
    fy: float,
    shift_std_px: tuple[float, float],
) -> FloatArray:
    """The covariance (2, 2; tangent angles, rad²) by which a depth-to-colour shift of std
    ``shift_std_px`` (du, dv) turns the plane of ``normal`` (see the module's docstring): the
    plane's (a, b, c) = n / d loses a du / fx + b dv / fy from c, so the unit normal moves by
    (I - n nᵀ) ẑ n_x / fx per pixel of du (and n_y / fy per pixel of dv)."""
    n = normal / np.linalg.norm(normal)
    across = np.array([0.0, 0.0, 1.0]) - n[2] * n  # (I - n nᵀ) ẑ
    g_u = basis @ across * (n[0] / fx)
    g_v = basis @ across * (n[1] / fy)
    su, sv = shift_std_px
    result: FloatArray = su**2 * np.outer(g_u, g_u) + sv**2 * np.outer(g_v, g_v)
    return result


def corners_normal(
    corners_xy: FloatArray,
    side_m: float,
    fx: float,
    fy: float,
    noise_px: float,
    reference: FloatArray,
) -> tuple[FloatArray, FloatArray] | None:
    """The code's normal (3,) from its four corners c0..c3 in undistorted normalised
    coordinates ``corners_xy`` (4, 2) and the printed square of side ``side_m`` (PnP, IPPE),
    and its covariance (2, 2; rad²) in ``tangent_basis(reference)``: corner noise ``noise_px``
    (per coordinate, pixels) through the Jacobian of the reprojection. Of IPPE's two solutions
    (a square seen nearly square on is ambiguous) the one nearer ``reference`` (the depth's
    normal) is taken. None when PnP finds nothing."""
    h = side_m / 2
    model = np.array([[h, -h, 0.0], [h, h, 0.0], [-h, h, 0.0], [-h, -h, 0.0]])
    try:
        count, rvecs, tvecs, _ = cv2.solvePnPGeneric(
            model, np.asarray(corners_xy, np.float64), np.eye(3), None, flags=cv2.SOLVEPNP_IPPE
        )
    except cv2.error:
        return None
    if count < 1:
        return None
    ref = reference / np.linalg.norm(reference)
    best: tuple[float, FloatArray, FloatArray] | None = None
    for rvec, tvec in zip(rvecs, tvecs, strict=False):
        rv, tv = np.asarray(rvec, np.float64).reshape(3), np.asarray(tvec, np.float64).reshape(3)
        if tv[2] <= 0:
            continue
        n = cv2.Rodrigues(rv)[0][:, 2]
        score = abs(float(n @ ref))
        if best is None or score > best[0]:
            best = (score, rv, tv)
    if best is None:
        return None
    _, rv, tv = best
    rotation = cv2.Rodrigues(rv)[0]
    normal: FloatArray = np.asarray(rotation[:, 2], np.float64)
    if float(normal @ ref) < 0:
        normal = -normal
    # Jacobian of the corners' pixels with respect to a small rotation w (camera frame, applied
    # on the left) and the translation, by central differences
    centred = model @ rotation.T  # the corners about the code's centre, camera axes
    scale = np.array([fx, fy])

    def pixels(w: FloatArray, t: FloatArray) -> FloatArray:
        p = centred @ cv2.Rodrigues(w)[0].T + t
        result: FloatArray = (p[:, :2] / p[:, 2:3] * scale).reshape(-1)
        return result

    jac = np.zeros((8, 6))
    step_w, step_t = 1e-6, 1e-6 * float(np.linalg.norm(tv))
    zero = np.zeros(3)
    for k in range(3):
        dw = np.zeros(3)
        dw[k] = step_w
        jac[:, k] = (pixels(dw, tv) - pixels(-dw, tv)) / (2 * step_w)
        dt = np.zeros(3)
        dt[k] = step_t
        jac[:, 3 + k] = (pixels(zero, tv + dt) - pixels(zero, tv - dt)) / (2 * step_t)
    info = jac.T @ jac
    try:
        cov6 = noise_px**2 * np.linalg.inv(info)
    except np.linalg.LinAlgError:
        return None
    # a small rotation w moves the normal by w × n: its tangent angles are (n × e_i) · w
    basis = tangent_basis(ref)
    a = np.vstack([np.cross(normal, basis[0]), np.cross(normal, basis[1])])
    cov: FloatArray = a @ cov6[:3, :3] @ a.T
    if not np.all(np.isfinite(cov)):
        return None
    return normal, cov


@dataclass(frozen=True)
class TiltFusion:
    """The fused normal (3,), how far it turned from the depth's (rad), the two inputs' stds
    and the result's (the larger principal std of each covariance, rad; the result's is the
    plane's when the corners were not used) and whether the corners were used."""

    normal: FloatArray
    turned_rad: float
    plane_std_rad: float
    corners_std_rad: float
    used: bool
    fused_std_rad: float


def _std(cov: FloatArray) -> float:
    return float(np.sqrt(max(float(np.linalg.eigvalsh(cov)[-1]), 0.0)))


def fuse_normals(
    plane_normal: FloatArray,
    plane_cov: FloatArray,
    other_normal: FloatArray,
    other_cov: FloatArray,
) -> TiltFusion:
    """The covariance-weighted mean of two normals (both covariances (2, 2) in
    ``tangent_basis(plane_normal)``), linearised about ``plane_normal``; the plane's normal
    when they disagree beyond DISAGREEMENT_SIGMAS or a covariance is singular."""
    n = plane_normal / np.linalg.norm(plane_normal)
    basis = tangent_basis(n)
    other = other_normal / np.linalg.norm(other_normal)
    if float(other @ n) < 0:
        other = -other
    delta = basis @ other  # tangent angles of the other normal (small)
    keep = TiltFusion(n, 0.0, _std(plane_cov), _std(other_cov), False, _std(plane_cov))
    try:
        combined = np.linalg.inv(plane_cov + other_cov)
        info_plane = np.linalg.inv(plane_cov)
        info_other = np.linalg.inv(other_cov)
    except np.linalg.LinAlgError:
        return keep
    if float(delta @ combined @ delta) > DISAGREEMENT_SIGMAS**2:
        return keep
    fused_cov = np.linalg.inv(info_plane + info_other)
    fused = fused_cov @ info_other @ delta
    normal = n + basis.T @ fused
    normal /= np.linalg.norm(normal)
    turned = float(np.arccos(np.clip(normal @ n, -1.0, 1.0)))
    return TiltFusion(
        normal, turned, keep.plane_std_rad, keep.corners_std_rad, True, _std(fused_cov)
    )
