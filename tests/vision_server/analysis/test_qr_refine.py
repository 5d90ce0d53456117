"""refine_corners' cheaper fit (issue 19, part 2): the rough sides stand in for the robust
line fit's first rounds without changing the corners it converges to."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from vision_server.analysis import qr

from .conftest import render_qr, square_corners


def test_seeded_fit_converges_to_the_corners_of_the_full_fit(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    # Rough corners up to 2 px off (zxing-cpp's p95 on renders is 1.6 px), blur up to 1.4 px:
    # seeding one round too many moves the corners here by up to 0.08 px.
    rng = np.random.default_rng(5)
    assert qr._FIT_SEEDED > 0  # the module's setting is the seeded fit
    for _ in range(6):
        angle = float(rng.uniform(0, 90))
        blur = float(rng.choice([0.0, 0.8, 1.4]))
        truth = square_corners((320, 240), 150, angle) + rng.uniform(-5, 5, (4, 2))
        img = render_qr("cellvision station 7", truth, blur_sigma=blur, noise_sigma=2, seed=3)
        rough = truth + rng.uniform(-2, 2, (4, 2))
        seeded = qr.refine_corners(img, rough)
        with monkeypatch.context() as m:
            m.setattr(qr, "_FIT_SEEDED", 0)
            full = qr.refine_corners(img, rough)
        np.testing.assert_allclose(seeded, full, atol=1e-9)
        assert float(np.abs(seeded - truth).max()) < 0.25


def test_a_code_too_large_for_one_row_of_samples_is_refined() -> None:
    # 1000 px a side: 480 profiles of 121 samples, more than cv2.remap's 32767 columns, so
    # the samples are read in rows (the one-row read of smaller codes would raise here).
    img = np.full((1100, 1100), 220, np.uint8)
    cv2.rectangle(img, (50, 50), (1049, 1049), 30, thickness=-1)
    truth = np.array([[49.5, 49.5], [1049.5, 49.5], [1049.5, 1049.5], [49.5, 1049.5]])
    rough = truth + np.array([[1.0, -1.0], [-1.0, 1.0], [1.0, 1.0], [-1.0, -1.0]])
    refined = qr.refine_corners(img, rough, modules=25)
    np.testing.assert_allclose(refined, truth, atol=0.05)


def test_an_image_too_large_for_cv2_remap_is_refined_in_a_view() -> None:
    # cv2.remap reads images under 32767 pixels a side: a code in a wider image is refined
    # in a view of its neighbourhood (without it, cv2.remap raises).
    img = np.full((240, 33000), 220, np.uint8)
    cv2.rectangle(img, (32700, 60), (32849, 209), 30, thickness=-1)
    truth = np.array([[32699.5, 59.5], [32849.5, 59.5], [32849.5, 209.5], [32699.5, 209.5]])
    rough = truth + np.array([[1.0, -1.0], [-1.0, 1.0], [1.0, 1.0], [-1.0, -1.0]])
    refined = qr.refine_corners(img, rough, modules=25)
    np.testing.assert_allclose(refined, truth, atol=0.05)
