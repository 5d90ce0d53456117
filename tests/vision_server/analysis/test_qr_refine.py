"""refine_corners' cheaper fit (issue 19, part 2): the rough sides stand in for the robust
line fit's first rounds without changing the corners it converges to."""

from __future__ import annotations

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
