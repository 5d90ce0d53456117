"""The sensor check: a depth camera's scale error and misregistration against colour, measured
on a QR board of known printed side. Here (numpy only) so that the server's
``vision-server sensor-check`` (saved views) and the robot client's ``sensor-check`` (views the
robot takes) fit and judge with one model.

Each ``qr_pose`` view of the board gives one number, ``depth_vs_side`` (how much further the
depth puts the board than its printed side does, relative) and its gain per pixel of
misregistration, ``shift_sensitivity`` (see :class:`.qr_pose.QRPoseQuality`):

    depth_vs_side_k = s + g_k · (du, dv) + noise

where s is the depth scale error (depth reads (1 + s) z) and (du, dv) px the shift (depth
pixel (u, v) saw colour pixel (u - du, v - dv)). Why this model: a plane's inverse depth is
linear in the normalised image coordinates, so shifting the depth image by (du, dv) moves the
fitted plane's distance by (n_x du / fx + n_y dv / fy) / n_z, which depends on the tilt; a
scale error moves it by s at every tilt. One view cannot separate the two; views tilted in
different directions can, by linear least squares over the views.

The printed side is the only absolute reference, so the corner detector's own bias on the
code's image side (``corner_bias_px``: -0.03 to -0.04 px on the simulated Xtion-like camera
with today's detector, -0.07 px with an earlier one; 0.03-0.1 % of the side at 0.7-1.3 m)
would otherwise pass for a depth scale error; it is removed as b / side_px per view. It is a
property of the detector at the camera's blur: measured against a known reference and
configured per inspection (qr_pose's ``corner_bias_px``, default 0), not fitted (a fit cannot
separate it from the scale over the usual range of distances).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

__all__ = [
    "SCALE_LIMIT",
    "SHIFT_LIMIT_PX",
    "DepthRegistration",
    "fit_depth_registration",
    "registration_advice",
]

SCALE_LIMIT = 0.002  # 0.2 %: 2 mm at 1 m, four times the QR pose goal
SHIFT_LIMIT_PX = 1.0  # ~0.8 mm at 1 m on a board 25° off square; the fit's noise is ~0.3 px

FloatArray = NDArray[np.float64]


@dataclass(frozen=True)
class DepthRegistration:
    """The fitted sensor errors.

    ``scale``: depth reads ``scale`` times the true z (1 + s). ``shift_px`` (du, dv): depth
    pixel (u, v) saw colour pixel (u - du, v - dv). ``scale_std`` and ``shift_std_px``: their
    standard errors from the fit's residuals (NaN for the shift when the views' tilts do not
    determine it). ``residual_rms``: RMS of the per-view residuals (relative). ``views``: how
    many views were used. These are what ``qr_pose``'s ``depth_scale`` and ``depth_shift_px``
    take to correct the sensor.
    """

    scale: float
    shift_px: tuple[float, float]
    scale_std: float
    shift_std_px: tuple[float, float]
    residual_rms: float
    views: int


def fit_depth_registration(
    depth_vs_side: Sequence[float] | FloatArray,
    shift_sensitivity: Sequence[Sequence[float]] | FloatArray,
    side_px: Sequence[float] | FloatArray | None = None,
    *,
    corner_bias_px: float = 0.0,
    min_tilt_spread: float = 2e-4,
    depth_vs_grid: Sequence[float] | FloatArray | None = None,
) -> DepthRegistration:
    """Least-squares fit of scale and shift over N views (see the module's docstring).

    ``depth_vs_grid`` (N,; NaN where not measured): the same disagreement from the code's
    module grid (``qr_pose``'s ``quality.depth_vs_grid``), used instead of the side's where it
    is finite, without ``corner_bias_px`` (the grid has no edge bias). Why: the corners' side
    carries a view-dependent error of ~0.02 px that no frame count averages out and a bias that
    changes with the view's foreshortening; on the simulated cell's oblique views (30-45°) the
    corners' fit was 0.6 px off in shift and 0.1 % in scale with 0.11 % residual RMS, the grid's
    0.03 px and 0.01 % with 0.01 % (issue 29).

    ``depth_vs_side`` (N,), ``shift_sensitivity`` (N, 2) and ``side_px`` (N,) from each
    view's quality report; with ``side_px``, the detector's ``corner_bias_px`` on the side is
    removed first (None: not removed).
    ``min_tilt_spread``: the smallest spread (std, per pixel) of the sensitivities below which
    the shift is not determined; it is then taken as (0, 0) with NaN uncertainty and only
    the scale is fitted.

    Raises ValueError with fewer than 2 finite views (or inputs of different lengths).
    """
    r = np.asarray(depth_vs_side, np.float64).reshape(-1)
    g = np.asarray(shift_sensitivity, np.float64).reshape(-1, 2)
    if r.size != g.shape[0]:
        raise ValueError(f"{r.size} ratios but {g.shape[0]} sensitivities")
    if side_px is not None:
        px = np.asarray(side_px, np.float64).reshape(-1)
        if px.size != r.size:
            raise ValueError(f"{r.size} ratios but {px.size} image sides")
        # the detector measured side_m (1 + bias / px): the depth's part is the rest
        r = (1.0 + r) / (1.0 + corner_bias_px / px) - 1.0
    if depth_vs_grid is not None:
        grid = np.asarray(depth_vs_grid, np.float64).reshape(-1)
        if grid.size != r.size:
            raise ValueError(f"{r.size} ratios but {grid.size} grid ratios")
        r = np.where(np.isfinite(grid), grid, r)
    ok = np.isfinite(r) & np.all(np.isfinite(g), axis=1)
    r, g = r[ok], g[ok]
    if r.size < 2:
        raise ValueError(
            f"the sensor check needs at least 2 views of the board with its side_m, got {r.size}"
        )
    spread = g.std(axis=0)
    fit_shift = bool(r.size >= 4 and np.all(spread >= min_tilt_spread))
    design = np.column_stack([np.ones(r.size), g]) if fit_shift else np.ones((r.size, 1))
    x, *_ = np.linalg.lstsq(design, r, rcond=None)
    residual = r - design @ x
    dof = max(r.size - design.shape[1], 1)
    sigma2 = float(residual @ residual) / dof
    cov = sigma2 * np.linalg.pinv(design.T @ design)
    std = np.sqrt(np.maximum(np.diag(cov), 0.0))
    if fit_shift:
        shift = (float(x[1]), float(x[2]))
        shift_std = (float(std[1]), float(std[2]))
    else:
        shift, shift_std = (0.0, 0.0), (float("nan"), float("nan"))
    return DepthRegistration(
        scale=1.0 + float(x[0]),
        shift_px=shift,
        scale_std=float(std[0]),
        shift_std_px=shift_std,
        residual_rms=float(np.sqrt(np.mean(residual**2))),
        views=int(r.size),
    )


def registration_advice(reg: DepthRegistration) -> tuple[bool, str]:
    """(within limits, what to do): scale beyond ``SCALE_LIMIT`` or a shift (when the views
    determined it) beyond ``SHIFT_LIMIT_PX`` needs the qr_pose inspection's correction."""
    off = []
    if abs(reg.scale - 1.0) > SCALE_LIMIT:
        off.append(f"depth scale {reg.scale:.4f} (limit ±{SCALE_LIMIT:.1%})")
    if np.isfinite(reg.shift_std_px[0]) and max(map(abs, reg.shift_px)) > SHIFT_LIMIT_PX:
        off.append(f"shift ({reg.shift_px[0]:+.2f}, {reg.shift_px[1]:+.2f}) px")
    if not off:
        return True, "the sensor agrees with the board: no depth correction needed"
    return False, (
        "; ".join(off) + ": set the qr_pose inspection's depth_scale, depth_shift_px and their "
        "_std keys to these values (or calibrate the sensor's depth-to-colour registration)"
    )
