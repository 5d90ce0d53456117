"""The QR bench splits the unchecked error along the camera's ray and across it (issue 18
part 3): a distance error must land along the ray, a sideways one across it."""

from __future__ import annotations

import numpy as np
import pytest

from bench.calibration import _along_and_lateral_mm
from geometry import make_transform, rotation_from_rpy


def test_a_distance_error_lies_along_the_ray_and_a_sideways_one_across() -> None:
    truth = make_transform(rotation_from_rpy(0.1, -0.2, 0.3), np.array([0.2, -0.1, 1.2]))
    ray = truth[:3, 3] / np.linalg.norm(truth[:3, 3])
    sideways = np.cross(ray, [0.0, 0.0, 1.0])
    sideways /= np.linalg.norm(sideways)
    est = truth.copy()
    est[:3, 3] += 0.002 * ray + 0.0005 * sideways  # 2 mm too far, 0.5 mm sideways
    along, lateral = _along_and_lateral_mm(est, truth)
    assert along == pytest.approx(2.0, abs=1e-9)
    assert lateral == pytest.approx(0.5, abs=1e-9)
    est[:3, 3] = truth[:3, 3] * 0.999  # scaled about the camera: too near, nothing across
    along, lateral = _along_and_lateral_mm(est, truth)
    assert along == pytest.approx(-1e-3 * np.linalg.norm(truth[:3, 3]) * 1e3, abs=1e-9)
    assert lateral == pytest.approx(0.0, abs=1e-9)
