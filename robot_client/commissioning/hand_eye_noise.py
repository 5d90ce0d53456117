"""What a hand-eye solution's residuals should be if only the measurements' noise were at work.

A hand-eye set can be self-consistent in pixels and still wrong by millimetres: with a focal
length 1.4 % off every view's board pose is scaled, the refinement absorbs most of it in the
camera's mount, and the reprojection RMS stays well under a pixel. The AX=XB loop does show it,
but only against what it would be from noise alone. This module gives that yardstick:

- the corners' noise: from the residuals of each view's board pose fitted freely
  (perspective-n-point), as the differences between neighbouring corners' residuals (a model
  error is smooth over the board and cancels there; noise does not), one variance for all
  views (pixels squared);
- the arm's repeatability: one standard deviation of where the tool truly ends against where
  the robot reports it (metres; radians of a turn about a random axis), as issue 18 and the
  simulated cell define it;

propagated linearly to the loop of every pair of views. Frames and units as in
docs/conventions.md.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from geometry import CameraIntrinsics, invert_transform

from .se3 import perturbed

FloatArray = NDArray[np.float64]

__all__ = ["DEFAULT_REPEATABILITY", "ExpectedResiduals", "Repeatability", "expected_residuals"]

_STEP = 1e-7  # finite-difference step of the linearisation (radians, metres)


@dataclass(frozen=True)
class Repeatability:
    """The arm's repeatability: one standard deviation of the tool's position (``m``,
    metres, per axis) and of its orientation (``rad``, radians, the angle of a turn about a
    random axis)."""

    m: float
    rad: float


DEFAULT_REPEATABILITY = Repeatability(0.03e-3, math.radians(0.01))
"""A good industrial arm's (a UR e-Series states +/-0.03 mm): the figure of issue 18."""


@dataclass(frozen=True)
class ExpectedResiduals:
    """The residuals noise alone gives: ``corner_noise_px`` (one standard deviation of a
    corner coordinate, from neighbouring corners' residuals of the free board poses),
    ``loop_translation_m`` and ``loop_rotation_rad`` (RMS over the pairs of views, as
    :class:`~robot_client.commissioning.hand_eye.HandEyeResult` reports the measured ones)
    and ``rms_px`` (the reprojection RMS of the joint solution)."""

    corner_noise_px: float
    loop_translation_m: float
    loop_rotation_rad: float
    rms_px: float


def _board_pose_jacobian(
    camera_from_board: FloatArray,
    corners_board: FloatArray,
    corners_uv: FloatArray,
    intrinsics: CameraIntrinsics,
) -> tuple[FloatArray, FloatArray]:
    """The corners' reprojection residual (2N) at ``camera_from_board`` and its Jacobian
    (2N, 6) against a :func:`perturbed` change of that pose."""

    def residual(delta: FloatArray) -> FloatArray:
        pose = perturbed(camera_from_board, delta)
        p = corners_board @ pose[:3, :3].T + pose[:3, 3]
        out: FloatArray = (intrinsics.project(p) - corners_uv).reshape(-1)
        return out

    r0 = residual(np.zeros(6))
    jacobian = np.zeros((r0.size, 6))
    for k in range(6):
        delta = np.zeros(6)
        delta[k] = _STEP
        jacobian[:, k] = (residual(delta) - residual(-delta)) / (2.0 * _STEP)
    return r0, jacobian


def expected_residuals(
    robot: Sequence[FloatArray],
    boards: Sequence[FloatArray],
    corners_board: Sequence[FloatArray],
    corners_uv: Sequence[FloatArray],
    x: FloatArray,
    intrinsics: CameraIntrinsics,
    repeatability: Repeatability = DEFAULT_REPEATABILITY,
    *,
    robot_is_inverse: bool = False,
) -> ExpectedResiduals:
    """The residuals of a solution ``x`` if the corners' noise (estimated from the views
    themselves) and the arm's ``repeatability`` were all that is wrong. ``robot``: each
    view's robot side (``base_from_tool`` eye-in-hand, its inverse eye-to-hand); ``boards``:
    each view's ``camera_from_board`` by perspective-n-point; ``robot_is_inverse``: the robot
    side is ``tool_from_base`` (eye-to-hand), whose error is still the tool's in the base."""

    def arm_moved(m: FloatArray, delta: FloatArray) -> FloatArray:
        if robot_is_inverse:
            return invert_transform(perturbed(invert_transform(m), delta))
        return perturbed(m, delta)

    squares, count_pairs = 0.0, 0
    jacobians = []
    for pose, board, uv in zip(boards, corners_board, corners_uv, strict=True):
        r0, jacobian = _board_pose_jacobian(pose, board, uv, intrinsics)
        total, pairs = _neighbour_differences(r0.reshape(-1, 2), board)
        squares += total
        count_pairs += pairs
        jacobians.append(jacobian)
    # |r_a - r_b|^2 of two neighbours holds 2 coordinates of twice the variance each.
    variance = squares / max(4 * count_pairs, 1)
    board_covs = [variance * np.linalg.pinv(j.T @ j) for j in jacobians]
    # The robot's error as :func:`perturbed` applies it: a turn of ``rad`` about a random axis
    # (rad^2 / 3 per axis) and ``m`` per axis.
    arm = np.diag([repeatability.rad**2 / 3.0] * 3 + [repeatability.m**2] * 3)
    # Each view's implied board pose Y_k = M_k X C_k and its covariance (perturbed()'s
    # coordinates: rotation vector on the left, translation) from its board pose and its arm.
    implied, spreads = [], []
    for m, c, board_cov in zip(robot, boards, board_covs, strict=True):
        y = m @ x @ c
        jacobian_y = np.zeros((6, 12))
        for k in range(12):
            delta = np.zeros(12)
            delta[k] = _STEP
            plus = arm_moved(m, delta[6:]) @ x @ perturbed(c, delta[:6])
            minus = arm_moved(m, -delta[6:]) @ x @ perturbed(c, -delta[:6])
            jacobian_y[:, k] = _pose_difference(plus, minus) / (2.0 * _STEP)
        cov = np.zeros((12, 12))
        cov[:6, :6], cov[6:, 6:] = board_cov, arm
        implied.append(y)
        spreads.append(jacobian_y @ cov @ jacobian_y.T)
    # The loop of views i and j is, to first order, Y_j against Y_i seen from the camera of
    # view i: (tau_j - tau_i) + (omega_j - omega_i) x (camera_i - board) for the translation,
    # omega_j - omega_i for the rotation; the views' errors are independent.
    loop_t, loop_r = [], []
    for i in range(len(robot)):
        lever = (robot[i] @ x)[:3, 3] - implied[i][:3, 3]
        g = np.hstack([-_skew(lever), np.eye(3)])
        for j in range(i + 1, len(robot)):
            loop_t.append(float(np.trace(g @ (spreads[i] + spreads[j]) @ g.T)))
            loop_r.append(float(np.trace(spreads[i][:3, :3] + spreads[j][:3, :3])))
    # The joint solution cannot follow the arm's error view by view: it shows in the pixels.
    shifted = 0.0
    count = 0
    for m, c, jacobian in zip(robot, boards, jacobians, strict=True):
        # The board pose the camera would see after a change d of the robot's side:
        # C' = X^-1 M'^-1 M X C; its Jacobian through the board pose's own.
        to_board = np.zeros((6, 6))
        for k in range(6):
            delta = np.zeros(6)
            delta[k] = _STEP
            plus = invert_transform(x) @ invert_transform(arm_moved(m, delta)) @ m @ x @ c
            minus = invert_transform(x) @ invert_transform(arm_moved(m, -delta)) @ m @ x @ c
            to_board[:, k] = _pose_difference(plus, minus) / (2.0 * _STEP)
        j_arm = jacobian @ to_board
        shifted += float(np.trace(j_arm @ arm @ j_arm.T))
        count += jacobian.shape[0] // 2
    rms_px = math.sqrt(2.0 * variance + shifted / max(count, 1))
    return ExpectedResiduals(
        math.sqrt(variance),
        math.sqrt(float(np.mean(loop_t))) if loop_t else 0.0,
        math.sqrt(float(np.mean(loop_r))) if loop_r else 0.0,
        rms_px,
    )


def _neighbour_differences(residual: FloatArray, corners_board: FloatArray) -> tuple[float, int]:
    """Sum of ``|r_a - r_b|^2`` (pixels squared) over neighbouring corners a, b (one square
    apart on the board) and the number of such pairs. A wrong model (intrinsics a little off)
    leaves residuals that change smoothly over the board, which a neighbour's cancels; the
    corners' noise does not cancel: so this measures the noise alone, where the residuals' own
    RMS would count the model's error as noise and excuse it."""
    if len(corners_board) < 2:
        return 0.0, 0
    gaps = np.linalg.norm(corners_board[:, None, :] - corners_board[None, :, :], axis=2)
    spacing = float(np.min(gaps[gaps > 0])) if np.any(gaps > 0) else 0.0
    a, b = np.nonzero(np.triu((gaps > 0) & (gaps < 1.01 * spacing)))
    differences = residual[a] - residual[b]
    return float(np.sum(differences**2)), len(a)


def _skew(v: FloatArray) -> FloatArray:
    """The matrix of ``v x``."""
    return np.array([[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]])


def _pose_difference(plus: FloatArray, minus: FloatArray) -> FloatArray:
    """``plus`` minus ``minus`` in :func:`perturbed`'s coordinates (rotation vector applied on
    the left, translation); the two are close (OpenCV's Rodrigues rounds so small a turn to
    nothing: its skew-symmetric part is the rotation vector to first order)."""
    d = plus[:3, :3] @ minus[:3, :3].T
    rotation = 0.5 * np.array([d[2, 1] - d[1, 2], d[0, 2] - d[2, 0], d[1, 0] - d[0, 1]])
    return np.concatenate([rotation, plus[:3, 3] - minus[:3, 3]])
