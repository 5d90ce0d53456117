"""Real photographs for accuracy tests: scikit-image's sample images, where installed.

scikit-image ships its classic sample photographs (``coins.png``, ``camera.png``, ...) inside
the package (``skimage/data/``). We read the files directly, without importing scikit-image
(which would pull in SciPy and more), so a tree with only the wheel's files is enough. Tests
that need them skip with :data:`MISSING` when the package is absent.
"""

from __future__ import annotations

import importlib.util
from pathlib import Path

import cv2
import numpy as np
from numpy.typing import NDArray

MISSING = (
    "scikit-image's sample photographs not found (pip install scikit-image: its wheel ships "
    "skimage/data/coins.png and the other classic images)"
)

UNRELATED = (
    "astronaut.png",
    "brick.png",
    "camera.png",
    "cell.png",
    "chelsea.png",
    "clock_motion.png",
    "coffee.png",
    "grass.png",
    "gravel.png",
    "hubble_deep_field.jpg",
    "ihc.png",
    "moon.png",
    "motorcycle_left.png",
    "motorcycle_right.png",
    "page.png",
    "retina.jpg",
    "rocket.jpg",
    "text.png",
)
"""scikit-image's photographs without a coin or other round part in them (the synthetic
drawings -- chessboard, logo, phantom, colour wheel -- are not photographs and are left out)."""


def skimage_data_dir() -> Path | None:
    """The ``skimage/data`` folder of an installed scikit-image, or None."""
    spec = importlib.util.find_spec("skimage")
    if spec is None or not spec.submodule_search_locations:
        return None
    for location in spec.submodule_search_locations:
        folder = Path(location) / "data"
        if (folder / "coins.png").is_file():
            return folder
    return None


def sample_gray(name: str) -> NDArray[np.uint8] | None:
    """scikit-image's sample ``name`` as a gray ``uint8`` image, or None when absent."""
    folder = skimage_data_dir()
    if folder is None or not (folder / name).is_file():
        return None
    image = cv2.imread(str(folder / name), cv2.IMREAD_GRAYSCALE)
    return None if image is None else np.asarray(image, np.uint8)


def degrade(
    image: NDArray[np.uint8], *, shift: tuple[float, float], sigma: float, gain: float
) -> NDArray[np.uint8]:
    """``image`` moved by ``shift`` = (du, dv) px (bilinear), blurred by a Gaussian of ``sigma``
    px (defocus), its grey levels scaled by ``gain`` (0.4: dimmed to 40 % contrast), rounded.

    Bilinear because its kernel's centroid is the shift asked for: OpenCV's Lanczos4 (tables
    in 1/32 px steps) moves the light by (0.325, 0.675) px for (0.3, 0.7)."""
    moved = cv2.warpAffine(
        image.astype(np.float32),
        np.array([[1, 0, shift[0]], [0, 1, shift[1]]], np.float32),
        (image.shape[1], image.shape[0]),
        flags=cv2.INTER_LINEAR,
        borderMode=cv2.BORDER_REFLECT,
    )
    if sigma > 0:
        moved = cv2.GaussianBlur(moved, (0, 0), sigma)
    return np.asarray(np.clip(np.rint(moved * gain), 0, 255), np.uint8)
