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

import cv2
import numpy as np
from numpy.typing import NDArray

from .backbone import Backbone, Features

GRID_STRIDE = 8
BANK_MAX = 8192
"""Bank members kept at most: scoring compares each of an image's cells (784 at 224x224) with
every member, about 2.3 GFLOP at this size."""
CANDIDATES_MAX = 60000
"""Cells the greedy selection looks at; beyond that, an even random sample of them."""
PROJECTION_DIMS = 64
DESCRIPTOR_DIMS = 24 + 40 + 112
MAX_INPUT = 1024
"""The largest input side a model file may ask for (px)."""
SMOOTH_SIGMA_PX = 4.0
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


def tap_scales(grids: Sequence[Features]) -> Array:
    """One factor per tap that makes each tap's mean squared descriptor norm 1 over ``grids``,
    so that no layer dominates the distance by its magnitude."""
    sums = np.zeros(3, np.float64)
    for features in grids:
        raw = describe(features)
        splits = np.cumsum([m.shape[2] for m in features.maps])[:-1]
        for i, part in enumerate(np.split(raw, splits, axis=2)):
            sums[i] += float(np.mean(np.sum(part.astype(np.float64) ** 2, axis=2)))
    means = sums / max(len(grids), 1)
    return (1.0 / np.sqrt(np.maximum(means, 1e-12))).astype(np.float32)


def _box3(tap: Array) -> Array:
    channels = tap.shape[2]
    # cv2 filters at most 512 channels at once; the taps have 24, 40 and 112
    assert channels <= 512
    return np.asarray(cv2.blur(tap, (3, 3), borderType=cv2.BORDER_REFLECT), np.float32)


def _resize(tap: Array, width: int, height: int, interpolation: int) -> Array:
    out = np.asarray(cv2.resize(tap, (width, height), interpolation=interpolation), np.float32)
    return out if out.ndim == 3 else out[:, :, None]


def select_bank(cells: Array, budget: int, rng: np.random.Generator) -> NDArray[np.int64]:
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
    points = cells[pool] @ projection
    chosen = np.empty(budget, np.int64)
    nearest = np.full(points.shape[0], np.inf, np.float32)
    pick = int(rng.integers(points.shape[0]))
    for i in range(budget):
        chosen[i] = pick
        step = points - points[pick]
        np.minimum(nearest, np.einsum("ij,ij->i", step, step), out=nearest)
        pick = int(np.argmax(nearest))
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


def train_bank(
    backbone: Backbone,
    images: Sequence[NDArray[np.uint8]],
    size: tuple[int, int],
    rng: np.random.Generator,
    progress: Callable[[str], None] | None = None,
) -> tuple[PatchBank, list[float]]:
    """A bank from good images, and each image's held-out score (against the bank without the
    members taken from it)."""
    features = []
    for index, image in enumerate(images):
        features.append(backbone.features(image, size))
        if progress is not None and (index + 1) % 10 == 0:
            progress(f"features of {index + 1}/{len(images)} images")
    scales = tap_scales(features)
    grids = [describe(f, scales) for f in features]
    cells_per_image = grids[0].shape[0] * grids[0].shape[1]
    cells = np.concatenate([g.reshape(cells_per_image, -1) for g in grids])
    sources = np.repeat(np.arange(len(grids), dtype=np.int32), cells_per_image)
    if progress is not None:
        progress(f"choosing at most {BANK_MAX} of {cells.shape[0]} patches")
    chosen = select_bank(cells, BANK_MAX, rng)
    bank = PatchBank(size, np.ascontiguousarray(cells[chosen]), scales, sources[chosen])
    held_out = [
        float(bank.heat(bank.cell_distances(grid, exclude=index)).max())
        for index, grid in enumerate(grids)
    ]
    return bank, held_out


__all__ = ["BANK_MAX", "PatchBank", "describe", "select_bank", "tap_scales", "train_bank"]
