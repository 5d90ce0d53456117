"""geometry: rigid transforms, the pinhole camera model and planes (numpy only, plus cv2 in tests).

Conventions are those of docs/conventions.md: transforms ``b_from_a`` are 4x4 float64 arrays
(``p_b = b_from_a @ p_a``), metres and radians, pixels ``(u, v)`` = (column, row), camera frame
x right / y down / z forward, distortion ``(k1, k2, p1, p2, k3)``.

Public API:

- transforms: ``make_transform(rotation, translation)``, ``invert_transform(b_from_a)``,
  ``transform_points(b_from_a, p_a)``, ``rotation_from_rpy(roll, pitch, yaw)`` /
  ``rpy_from_rotation(rotation)`` (extrinsic X-Y-Z: ``R = Rz(yaw) Ry(pitch) Rx(roll)``),
  ``rotation_from_axis_angle(axis, angle)``, ``rotation_angle(rotation)``,
  ``orthonormalize(matrix)``, ``transform_from_xyz_rpy(xyz, rpy)``,
  ``xyz_rpy_from_transform(b_from_a)``.
- camera: ``CameraIntrinsics`` (``matrix``, ``project``, ``distort_normalized``,
  ``undistort_pixels``, ``pixel_rays``, ``backproject``, ``scaled``).
- planes: ``intersect_ray_plane(origin, direction, plane_point, plane_normal)``,
  ``fit_plane(points, *, ransac_threshold_m=None, rng=None) -> PlaneFit(normal, d, inliers, rms)``.
"""

from geometry.camera import CameraIntrinsics
from geometry.planes import PlaneFit, fit_plane, intersect_ray_plane
from geometry.transforms import (
    invert_transform,
    make_transform,
    orthonormalize,
    rotation_angle,
    rotation_from_axis_angle,
    rotation_from_rpy,
    rpy_from_rotation,
    transform_from_xyz_rpy,
    transform_points,
    xyz_rpy_from_transform,
)

__all__ = [
    "CameraIntrinsics",
    "PlaneFit",
    "fit_plane",
    "intersect_ray_plane",
    "invert_transform",
    "make_transform",
    "orthonormalize",
    "rotation_angle",
    "rotation_from_axis_angle",
    "rotation_from_rpy",
    "rpy_from_rotation",
    "transform_from_xyz_rpy",
    "transform_points",
    "xyz_rpy_from_transform",
]
