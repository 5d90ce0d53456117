"""deblur_axis: a box motion blur along one axis undone, the other axis untouched."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from vision_server.analysis.deblur import deblur_axis


def _bars(rng: np.random.Generator) -> np.ndarray:
    """Random dark/light bars 3..8 px wide across a 40 x 240 image (values 40 and 210)."""
    widths = rng.integers(3, 9, size=60)
    row = np.concatenate([np.full(w, 40 if k % 2 else 210) for k, w in enumerate(widths)])
    return np.tile(row[:240], (40, 1)).astype(np.float32)


@pytest.mark.parametrize("axis", [1, 0])
def test_a_box_blur_along_the_axis_is_undone(axis: int) -> None:
    sharp = _bars(np.random.default_rng(3))
    if axis == 0:
        sharp = np.ascontiguousarray(sharp.T)
    ksize = (5, 1) if axis == 1 else (1, 5)  # odd: centred as deblur_axis assumes
    blurred = np.clip(cv2.blur(sharp, ksize), 0, 255).astype(np.uint8)
    # noise-free input: a light regularisation restores the bars nearly exactly
    (length, restored), *_ = deblur_axis(blurred, [5], axis=axis, noise_to_signal=1e-3)
    assert length == 5
    assert restored.shape == blurred.shape
    assert restored.dtype == np.uint8

    def residual(img: np.ndarray) -> float:
        # RMS misfit to the sharp bars after the best gain and offset (the output is
        # stretched), away from the ends
        inner = (slice(None), slice(20, -20)) if axis == 1 else (slice(20, -20), slice(None))
        x = img[inner].astype(np.float64).ravel()
        y = sharp[inner].astype(np.float64).ravel()
        design = np.stack([x, np.ones_like(x)], axis=1)
        fit, *_ = np.linalg.lstsq(design, y, rcond=None)
        return float(np.sqrt(np.mean((design @ fit - y) ** 2)))

    assert residual(restored) < 0.5 * residual(blurred), (residual(restored), residual(blurred))


def test_each_length_is_yielded_in_order_and_lazily() -> None:
    img = np.full((20, 30), 128, np.uint8)
    copies = deblur_axis(img, [3, 5, 8])
    assert next(copies)[0] == 3
    assert [n for n, _ in copies] == [5, 8]


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"lengths_px": [1]}, "lengths_px must be >= 2"),
        ({"lengths_px": [4], "noise_to_signal": 0.0}, "noise_to_signal must be > 0"),
        ({"lengths_px": [4], "axis": 2}, "axis must be 0 or 1"),
    ],
)
def test_bad_arguments_are_value_errors_naming_them(kwargs: dict, match: str) -> None:
    with pytest.raises(ValueError, match=match):
        next(deblur_axis(np.zeros((10, 10), np.uint8), **kwargs))
