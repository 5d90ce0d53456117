"""``variation``: the classical variation model of aligned parts (no learned weights).

The good images, aligned (a fixtured ROI), give each pixel a mean grey level and a spread (the
standard deviation over the images). A new image's deviation at a pixel is its distance from the
mean in units of the spread, floored so that pixels that never varied are not infinitely strict;
the heat map is that deviation smoothed over a few pixels (a single noisy pixel is not a
defect), and the score is its maximum.

Units: the heat map and the score are in spreads (standard deviations); 4 means four of them.
Images are worked on at ``size`` (width, height), at most 512 px a side.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import cv2
import numpy as np
from numpy.typing import NDArray

MAX_SIDE = 512
SPREAD_FLOOR = 4.0
"""Grey levels: the least spread a pixel is given (sensor noise on 8 bits is about 1-3)."""
PRE_BLUR_SIGMA = 1.0
SMOOTH_SIGMA = 2.0

Array = NDArray[np.float32]


def working_size(width: int, height: int) -> tuple[int, int]:
    """The size an image of ``width`` x ``height`` px is compared at (the longer side at most
    512 px, aspect kept)."""
    scale = min(1.0, MAX_SIDE / max(width, height))
    return max(8, round(width * scale)), max(8, round(height * scale))


def _grey(image: NDArray[np.uint8], size: tuple[int, int]) -> Array:
    grey = image if image.ndim == 2 else cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
    if (grey.shape[1], grey.shape[0]) != size:
        grey = cv2.resize(grey, size, interpolation=cv2.INTER_AREA)
    blurred = cv2.GaussianBlur(grey.astype(np.float32), (0, 0), PRE_BLUR_SIGMA)
    return np.asarray(blurred, np.float32)


@dataclass(frozen=True)
class VariationModel:
    """``size`` (width, height) the working size in px; ``mean`` and ``spread`` (H, W) grey
    levels at that size."""

    size: tuple[int, int]
    mean: Array
    spread: Array

    def heat(self, image: NDArray[np.uint8]) -> Array:
        return self._heat(_grey(image, self.size), self.mean, self.spread)

    @staticmethod
    def _heat(grey: Array, mean: Array, spread: Array) -> Array:
        deviation = np.abs(grey - mean) / spread
        return np.asarray(cv2.GaussianBlur(deviation, (0, 0), SMOOTH_SIGMA), np.float32)


def train_variation(
    images: Sequence[NDArray[np.uint8]], size: tuple[int, int]
) -> tuple[VariationModel, list[float]]:
    """The model of the good ``images`` (all the same size), and each image's held-out score:
    against the mean and spread of the other images."""
    greys = [_grey(image, size) for image in images]
    count = len(greys)
    total = np.zeros_like(greys[0], dtype=np.float64)
    squares = np.zeros_like(total)
    for grey in greys:
        total += grey
        squares += grey.astype(np.float64) ** 2
    model = VariationModel(size, *_moments(total, squares, count))
    held_out = []
    for grey in greys:
        mean, spread = _moments(total - grey, squares - grey.astype(np.float64) ** 2, count - 1)
        held_out.append(float(VariationModel._heat(grey, mean, spread).max()))
    return model, held_out


def _moments(
    total: NDArray[np.float64], squares: NDArray[np.float64], count: int
) -> tuple[Array, Array]:
    mean = total / count
    variance = np.maximum(squares / count - mean**2, 0.0) * count / max(count - 1, 1)
    spread = np.maximum(np.sqrt(variance), SPREAD_FLOOR)
    return mean.astype(np.float32), spread.astype(np.float32)


__all__ = ["MAX_SIDE", "VariationModel", "train_variation", "working_size"]
