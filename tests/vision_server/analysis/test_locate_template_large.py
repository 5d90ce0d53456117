"""A template larger than 181 x 181 pixels (more points than one row of ``cv2.remap``'s maps
may hold, 32767): the alignment samples it in rows, so that a template trained in the console
(up to 1024 x 1024 px) locates its part instead of failing inside OpenCV."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from vision_server.analysis.locate import locate_template


@pytest.mark.parametrize("side", [182, 240, 400])
def test_a_large_template_is_located_at_its_sub_pixel_place(side: int) -> None:
    rng = np.random.default_rng(side)
    texture = rng.integers(0, 256, (side // 8 + 2, side // 8 + 2)).astype(np.float32)
    part = cv2.resize(texture, (side + 16, side + 16), interpolation=cv2.INTER_CUBIC)
    part = np.clip(part, 0, 255).astype(np.uint8)
    template = part[8 : 8 + side, 8 : 8 + side]
    image = np.full((side + 200, side + 240), 128, np.uint8)
    top, left = 90, 110
    image[top - 8 : top - 8 + side + 16, left - 8 : left - 8 + side + 16] = part
    (feature,) = locate_template(image, template)
    assert feature.u == pytest.approx(left + (side - 1) / 2, abs=0.05)
    assert feature.v == pytest.approx(top + (side - 1) / 2, abs=0.05)
    assert feature.score > 0.99
