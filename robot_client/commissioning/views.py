"""Poses of a tool camera over a calibration board, spread for intrinsics calibration.

The board frame is OpenCV's (origin at the top-left corner of the squares, x right, y down
the print, z into the board, metres), the camera frame x right, y down, z forward. A view
looks at a point of the board from a distance with a tilt and a roll; the set mixes frontal
views with the board in the middle and in each corner of the image (the distortion is seen
near the image's edges) and views tilted by ``tilt_deg`` every way (which separate the focal
length from the distance).
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import NDArray

from geometry import invert_transform, make_transform, rotation_from_axis_angle

__all__ = ["board_from_camera_views", "plan_tool_views"]

FloatArray = NDArray[np.float64]


def _view(
    target: FloatArray, distance_m: float, tilt_x_deg: float, tilt_y_deg: float, roll_deg: float
) -> FloatArray:
    """``board_from_camera`` of a camera ``distance_m`` from ``target`` (board frame) looking
    at it, tilted about the board's x and y axes and rolled about its optical axis."""
    rotation = (
        rotation_from_axis_angle((0.0, 1.0, 0.0), math.radians(tilt_y_deg))
        @ rotation_from_axis_angle((1.0, 0.0, 0.0), math.radians(tilt_x_deg))
        @ rotation_from_axis_angle((0.0, 0.0, 1.0), math.radians(roll_deg))
    )
    position = target - rotation[:, 2] * distance_m
    return make_transform(rotation, position)


def board_from_camera_views(
    board_size_m: tuple[float, float],
    *,
    fx_px: float,
    image_width_px: int,
    tilt_deg: float = 30.0,
    fill: float = 0.8,
) -> list[FloatArray]:
    """15 camera poses ``board_from_camera`` (4x4) over a board of ``board_size_m`` (width,
    height of its squares' area): at the distance where the board fills ``fill`` of the image
    width (pinhole with ``fx_px``; 0.8 puts corners near the image's edges, which pins the
    distortion and so the principal point: with 0.6 the principal point's standard deviation
    was 0.5 px in the simulated cell, with 0.8 0.38 px), 5 frontal views (centred, and aimed
    so that the board lies in each corner of the image), 8 tilted by ``tilt_deg`` (4 ways,
    and 4 diagonals with a roll) and 2 rolled by +-90 degrees."""
    width, height = board_size_m
    centre = np.array([width / 2, height / 2, 0.0])
    distance = fx_px * width / (fill * image_width_px)
    sx, sy = 0.3 * width, 0.3 * height
    views = [_view(centre, distance, 0.0, 0.0, 0.0)]
    views += [
        _view(centre + np.array([dx, dy, 0.0]), distance, 0.0, 0.0, 0.0)
        for dx, dy in ((sx, sy), (-sx, sy), (sx, -sy), (-sx, -sy))
    ]
    views += [
        _view(centre, distance, ax, ay, 0.0)
        for ax, ay in ((tilt_deg, 0.0), (-tilt_deg, 0.0), (0.0, tilt_deg), (0.0, -tilt_deg))
    ]
    diagonal = tilt_deg / math.sqrt(2.0)
    views += [
        _view(centre, distance, ax, ay, roll)
        for ax, ay, roll in (
            (diagonal, diagonal, 15.0),
            (-diagonal, diagonal, -15.0),
            (diagonal, -diagonal, -15.0),
            (-diagonal, -diagonal, 15.0),
        )
    ]
    views += [_view(centre, distance * 0.9, 0.0, 0.0, roll) for roll in (90.0, -90.0)]
    return views


def plan_tool_views(
    base_from_board: FloatArray,
    tool_from_camera: FloatArray,
    board_size_m: tuple[float, float],
    *,
    fx_px: float,
    image_width_px: int,
    tilt_deg: float = 30.0,
) -> list[FloatArray]:
    """Tool poses ``base_from_tool`` (4x4) that put the camera at each of
    :func:`board_from_camera_views`; ``base_from_board`` in OpenCV's board frame (as measured
    from a first view), ``tool_from_camera`` the camera's mount (nominal is enough)."""
    camera_from_tool = invert_transform(tool_from_camera)
    return [
        base_from_board @ board_from_camera @ camera_from_tool
        for board_from_camera in board_from_camera_views(
            board_size_m, fx_px=fx_px, image_width_px=image_width_px, tilt_deg=tilt_deg
        )
    ]
