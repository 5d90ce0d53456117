"""``patches``: a memory bank of good patches' features (PatchCore-style), scored by distance.

Each image is described on a grid at stride 8 of the model's input: at every cell, the features
of Lite0's blocks 2, 4 and 10 (stride 4, 8 and 16), each averaged over its 3x3 neighbourhood and
brought to the stride-8 grid, scaled so that every tap weighs the same, then concatenated. A
bank keeps a subset of the good images' cells chosen to cover them all (greedy k-centre on a
random projection). A cell's anomaly is the distance to its nearest bank member; the heat map is
that distance per cell, smoothed; the image's score is the heat map's maximum.

Units: feature distances (dimensionless), the same units as the threshold.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray

from .backbone import Backbone, Features

GRID_STRIDE = 8
BANK_MAX = 8192
"""Bank members kept at most: scoring compares each of an image's cells (784 at 224x224) with
every member, about 2.3 GFLOP at this size."""
CANDIDATES_MAX = 40000
"""Cells the greedy selection looks at; beyond that, an even random sample of them."""
PROJECTION_DIMS = 64
DESCRIPTOR_DIMS = 24 + 40 + 112
MAX_INPUT = 448
"""The largest input side a model file may ask for (px)."""
SMOOTH_SIGMA_PX = 2.0
"""The heat map's Gaussian smoothing at the model's input scale (PatchCore's)."""

Array = NDArray[np.float32]


def describe(features: Features, scales: Array | None = None) -> Array:
    """The (H/8, W/8, D) descriptor grid of one image's tap maps (strides 4, 8, 16)."""
    fine, middle, coarse = features.maps
    rows, cols = middle.shape[:2]
    parts: list[Array] = []
    for tap in (fine, middle, coarse):
        local = _box3(tap)
        if local.shape[0] != rows:
            interpolation = cv2.INTER_AREA if local.shape[0] > rows else cv2.INTER_LINEAR
            local = _resize(local, cols, rows, interpolation)
        parts.append(local)
    if scales is not None:
        parts = [part * scale for part, scale in zip(parts, scales, strict=True)]
    return np.ascontiguousarray(np.concatenate(parts, axis=2), dtype=np.float32)


TAP_WEIGHTS = (2.0, 1.0, 0.5)
"""How much each tap (stride 4, 8, 16) counts in the distance, once their magnitudes are
equalised.

Chosen with :data:`SMOOTH_SIGMA_PX`, :data:`TOP_FRACTION` and the input side (256 px,
:mod:`.model`) on the bench's hardest six parts (tests/helpers/anomaly_parts.py: grass, gravel,
page, coffee, camera, coins; 30 good images, 20 held-out good and 18 defects each; mean/worst
image AUROC): 224 px, weights 1, 1, 0.5, sigma 4, the maximum 0.759/0.556; weights 2, 1, 0.5
0.795/0.642; with the top 1 % 0.815/0.700, sigma 2 0.825/0.725; 256 px 0.864/0.747; the top
0.3 % 0.867/0.781. Not better: 288 or 320 px (0.854, 0.856), weights 3, 1, 0.5 (0.861) or
2, 1, 1 (0.863), the top 0.1 % (0.852). The deep tap stays at half weight for defects larger
than a cell (a missing piece)."""

TOP_FRACTION = 0.003
"""An image's score: the mean of the heat map's highest 0.3 % (at 256x256 about 200 px, a
defect's core), steadier than the single hottest pixel."""


def image_score(heat: Array) -> float:
    """The score of a heat map: the mean of its highest :data:`TOP_FRACTION`."""
    flat = heat.ravel()
    count = max(1, int(flat.size * TOP_FRACTION))
    return float(np.partition(flat, flat.size - count)[flat.size - count :].mean())


def tap_scales(grids: Sequence[Features]) -> Array:
    """One factor per tap that makes each tap's mean squared descriptor norm its weight squared
    (:data:`TAP_WEIGHTS`) over ``grids``, so that no layer dominates the distance by its
    magnitude."""
    sums = np.zeros(3, np.float64)
    for features in grids:
        raw = describe(features)
        splits = np.cumsum([m.shape[2] for m in features.maps])[:-1]
        for i, part in enumerate(np.split(raw, splits, axis=2)):
            sums[i] += float(np.mean(np.sum(part.astype(np.float64) ** 2, axis=2)))
    means = sums / max(len(grids), 1)
    weights = np.asarray(TAP_WEIGHTS, np.float64)
    return (weights / np.sqrt(np.maximum(means, 1e-12))).astype(np.float32)


def _box3(tap: Array) -> Array:
    channels = tap.shape[2]
    # cv2 filters at most 512 channels at once; the taps have 24, 40 and 112
    assert channels <= 512
    return np.asarray(cv2.blur(tap, (3, 3), borderType=cv2.BORDER_REFLECT), np.float32)


def _resize(tap: Array, width: int, height: int, interpolation: int) -> Array:
    out = np.asarray(cv2.resize(tap, (width, height), interpolation=interpolation), np.float32)
    return out if out.ndim == 3 else out[:, :, None]


def select_bank(
    cells: NDArray[np.floating[Any]],
    budget: int,
    rng: np.random.Generator,
    progress: Callable[[str], None] | None = None,
) -> NDArray[np.int64]:
    """Indices of at most ``budget`` rows of ``cells`` (N, D) that cover them: each pick is the
    row farthest from those already picked (greedy k-centre), measured on a random projection."""
    count = cells.shape[0]
    if count <= budget:
        return np.arange(count)
    pool = np.arange(count)
    if count > CANDIDATES_MAX:
        pool = np.sort(rng.choice(count, CANDIDATES_MAX, replace=False))
    dims = min(PROJECTION_DIMS, cells.shape[1])
    projection = rng.standard_normal((cells.shape[1], dims)).astype(np.float32) / np.sqrt(dims)
    points = np.empty((pool.size, dims), np.float32)
    for start in range(0, pool.size, 8192):
        part = pool[start : start + 8192]
        points[start : start + part.size] = cells[part].astype(np.float32) @ projection
    chosen = np.empty(budget, np.int64)
    nearest = np.full(points.shape[0], np.inf, np.float32)
    norms = np.einsum("ij,ij->i", points, points)
    squared = np.empty_like(nearest)
    pick = int(rng.integers(points.shape[0]))
    for i in range(budget):
        chosen[i] = pick
        # |p - q|^2 = |p|^2 - 2 p.q + |q|^2: one matrix-vector product, no (N, D) temporary
        np.dot(points, points[pick], out=squared)
        squared *= -2.0
        squared += norms
        squared += norms[pick]
        np.minimum(nearest, squared, out=nearest)
        pick = int(np.argmax(nearest))
        if progress is not None and (i + 1) % 1024 == 0:
            progress(f"chose {i + 1}/{budget} patches")
    return pool[chosen]


@dataclass(frozen=True)
class PatchBank:
    """A trained bank: ``size`` the model's input (width, height) in px, ``members`` (M, D),
    ``scales`` one factor per tap, ``sources`` each member's training image index."""

    size: tuple[int, int]
    members: Array
    scales: Array
    sources: NDArray[np.int32]

    def grid(self, backbone: Backbone, image: NDArray[np.uint8]) -> Array:
        return describe(backbone.features(image, self.size), self.scales)

    def cell_distances(self, grid: Array, exclude: int | None = None) -> Array:
        """Each cell's distance to its nearest member (H/8, W/8); ``exclude``: leave out the
        members taken from that training image (its held-out score)."""
        rows, cols, dims = grid.shape
        queries = grid.reshape(-1, dims)
        squared = (
            np.einsum("ij,ij->i", queries, queries)[:, None]
            - 2.0 * (queries @ self.members.T)
            + _norms(self.members)[None, :]
        )
        if exclude is not None:
            squared[:, self.sources == exclude] = np.inf
        nearest = np.maximum(squared.min(axis=1), 0.0)
        return np.asarray(np.sqrt(nearest).reshape(rows, cols), np.float32)

    def heat(self, distances: Array) -> Array:
        """The cell distances as a smoothed map at the model's input size."""
        width, height = self.size
        full = cv2.resize(distances, (width, height), interpolation=cv2.INTER_LINEAR)
        return np.asarray(cv2.GaussianBlur(full, (0, 0), SMOOTH_SIGMA_PX), np.float32)


def _norms(members: Array) -> Array:
    return np.asarray(np.einsum("ij,ij->i", members, members), np.float32)


FOLDS = 5
"""Held-out scores come from a 5-fold split of the good images (image i in fold i mod 5)."""
SCALE_IMAGES = 32
"""Images whose features set the taps' scales (the rest are described as they come)."""


def train_bank(
    backbone: Backbone,
    images: Sequence[NDArray[np.uint8]],
    size: tuple[int, int],
    rng: np.random.Generator,
    progress: Callable[[str], None] | None = None,
) -> tuple[PatchBank, list[float]]:
    """A bank from good images, and each image's held-out score (against a bank chosen without
    its fold, :data:`FOLDS`). ``progress`` is called every few images and picks (it may raise to
    stop the training). Memory: each image's cells are kept as float16, about 0.28 MB an
    image at 224x224."""
    report = progress or (lambda _message: None)
    first = [backbone.features(image, size) for image in images[:SCALE_IMAGES]]
    scales = tap_scales(first)
    grid0 = describe(first[0], scales)
    rows, cols, dims = grid0.shape
    per_image = rows * cols
    cells = np.empty((len(images), per_image, dims), np.float16)
    for index, image in enumerate(images):
        features = first[index] if index < len(first) else backbone.features(image, size)
        cells[index] = describe(features, scales).reshape(per_image, dims)
        if (index + 1) % 10 == 0:
            report(f"features of {index + 1}/{len(images)} images")
    del first
    flat = cells.reshape(-1, dims)
    sources = np.repeat(np.arange(len(images), dtype=np.int32), per_image)
    report(f"choosing at most {BANK_MAX} of {flat.shape[0]} patches")
    chosen = select_bank(flat, BANK_MAX, rng, report)
    members = np.ascontiguousarray(flat[chosen], dtype=np.float32)
    bank = PatchBank(size, members, scales, sources[chosen])
    # Held-out scores: each fold's images against a bank chosen from the other folds only.
    # (Leaving an image's own members out of the whole bank was not enough: the bank was still
    # chosen to cover that image, and new good parts failed four times the target rate.)
    folds = min(FOLDS, len(images))
    held_out = [0.0] * len(images)
    for fold in range(folds):
        inside = np.arange(len(images)) % folds != fold
        others = cells[inside].reshape(-1, dims)
        picked = select_bank(others, BANK_MAX, rng, report)
        fold_bank = PatchBank(
            size, np.ascontiguousarray(others[picked], dtype=np.float32), scales, sources[:0]
        )
        for held in np.flatnonzero(~inside).tolist():
            grid = cells[held].astype(np.float32).reshape(rows, cols, dims)
            held_out[held] = image_score(fold_bank.heat(fold_bank.cell_distances(grid)))
        report(f"held-out scores of fold {fold + 1}/{folds}")
    return bank, held_out


__all__ = ["BANK_MAX", "PatchBank", "describe", "select_bank", "tap_scales", "train_bank"]
