"""Seeded invariants of the transform helpers."""

from __future__ import annotations

import numpy as np
import pytest

from geometry import (
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


def _random_rotation(rng: np.random.Generator) -> np.ndarray:
    q = rng.normal(size=4)
    q /= np.linalg.norm(q)
    w, x, y, z = q
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
            [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
            [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
        ]
    )


def _random_transform(rng: np.random.Generator) -> np.ndarray:
    return make_transform(_random_rotation(rng), rng.uniform(-2, 2, size=3))


def test_invert_then_compose_is_identity() -> None:
    rng = np.random.default_rng(1)
    for _ in range(50):
        b_from_a = _random_transform(rng)
        a_from_b = invert_transform(b_from_a)
        np.testing.assert_allclose(a_from_b @ b_from_a, np.eye(4), atol=1e-12)
        np.testing.assert_allclose(a_from_b, np.linalg.inv(b_from_a), atol=1e-12)


def test_transform_points_matches_homogeneous_product_and_composes() -> None:
    rng = np.random.default_rng(2)
    c_from_b = _random_transform(rng)
    b_from_a = _random_transform(rng)
    p_a = rng.uniform(-1, 1, size=(20, 3))
    p_b = transform_points(b_from_a, p_a)
    homog = (b_from_a @ np.c_[p_a, np.ones(20)].T).T[:, :3]
    np.testing.assert_allclose(p_b, homog, atol=1e-12)
    np.testing.assert_allclose(
        transform_points(c_from_b @ b_from_a, p_a), transform_points(c_from_b, p_b), atol=1e-12
    )
    assert transform_points(b_from_a, p_a[0]).shape == (3,)


def test_rpy_convention_is_extrinsic_xyz() -> None:
    roll, pitch, yaw = 0.3, -0.4, 1.1
    R = rotation_from_rpy(roll, pitch, yaw)
    Rx = rotation_from_axis_angle([1, 0, 0], roll)
    Ry = rotation_from_axis_angle([0, 1, 0], pitch)
    Rz = rotation_from_axis_angle([0, 0, 1], yaw)
    np.testing.assert_allclose(R, Rz @ Ry @ Rx, atol=1e-12)


def test_rpy_round_trip_including_gimbal_lock() -> None:
    rng = np.random.default_rng(3)
    for _ in range(100):
        R = _random_rotation(rng)
        np.testing.assert_allclose(rotation_from_rpy(*rpy_from_rotation(R)), R, atol=1e-9)
    for pitch in (np.pi / 2, -np.pi / 2):
        R = rotation_from_rpy(0.4, pitch, -0.7)
        np.testing.assert_allclose(rotation_from_rpy(*rpy_from_rotation(R)), R, atol=1e-9)


def test_xyz_rpy_round_trip() -> None:
    T = transform_from_xyz_rpy([0.1, -0.2, 0.3], [0.1, 0.2, -0.3])
    xyz, rpy = xyz_rpy_from_transform(T)
    np.testing.assert_allclose(xyz, [0.1, -0.2, 0.3])
    np.testing.assert_allclose(rpy, [0.1, 0.2, -0.3], atol=1e-12)


def test_axis_angle_and_rotation_angle() -> None:
    rng = np.random.default_rng(4)
    for angle in [0.0, 1e-7, 0.01, 1.0, 3.0, np.pi]:
        axis = rng.normal(size=3)
        R = rotation_from_axis_angle(axis, angle)
        np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-12)
        assert np.linalg.det(R) == pytest.approx(1.0)
        assert rotation_angle(R) == pytest.approx(angle, abs=1e-9)
        # The axis is fixed by the rotation.
        np.testing.assert_allclose(R @ axis, axis, atol=1e-12)


def test_orthonormalize_recovers_rotation() -> None:
    rng = np.random.default_rng(5)
    R = _random_rotation(rng)
    noisy = R + rng.normal(scale=1e-3, size=(3, 3))
    fixed = orthonormalize(noisy)
    np.testing.assert_allclose(fixed @ fixed.T, np.eye(3), atol=1e-12)
    assert np.linalg.det(fixed) == pytest.approx(1.0)
    assert rotation_angle(R.T @ fixed) < 5e-3
    np.testing.assert_allclose(orthonormalize(R), R, atol=1e-12)


@pytest.mark.parametrize(
    ("call", "argument"),
    [
        (lambda: make_transform(np.eye(2), [0, 0, 0]), "rotation"),
        (lambda: make_transform(np.eye(3), [0, 0]), "translation"),
        (lambda: invert_transform(np.eye(3)), "b_from_a"),
        (lambda: transform_points(np.eye(4), np.zeros((3, 2))), "p_a"),
        (lambda: rotation_from_axis_angle([0, 0, 0], 1.0), "axis"),
    ],
)
def test_bad_arguments_are_named(call: object, argument: str) -> None:
    with pytest.raises(ValueError, match=argument):
        call()  # type: ignore[operator]
