"""The anomaly inspection's test parts (tests/helpers/anomaly_parts.py): deterministic, of the
asked size, each defect visible inside its mask and of modest size, good samples that vary like
a fixtured part's; and the AUROC against hand-computed values."""

from __future__ import annotations

import itertools

import cv2
import numpy as np
import pytest

from tests.helpers.anomaly_parts import (
    DEFECTS,
    PHOTO_PARTS,
    SYNTHETIC_PARTS,
    auroc,
    part_samples,
    photo_available,
    synthetic_part,
)
from tests.helpers.photos import MISSING

PHOTOS = {p.name for p in PHOTO_PARTS}


def test_auroc_against_hand_computed_values() -> None:
    assert auroc([1, 2, 3], [4, 5]) == 1.0
    assert auroc([4, 5], [1, 2, 3]) == 0.0
    # pairs (defect, good): 2>1 1, 2=2 0.5, 2<3 0, 4 over all three 3: 4.5 of 6
    assert auroc([1, 2, 3], [2, 4]) == pytest.approx(0.75)
    assert auroc([7, 7], [7, 7, 7]) == pytest.approx(0.5)
    # 0.5 > 0.2, 0.5 = 0.5, 0.5 < 0.9; 0.9 > 0.2, 0.9 > 0.5, 0.9 = 0.9: (1 + .5 + 0 + 2.5) / 6
    assert auroc([0.2, 0.5, 0.9], [0.5, 0.9]) == pytest.approx(4 / 6)


def test_auroc_is_the_pairwise_count_with_ties_half() -> None:
    rng = np.random.default_rng(3)
    good = rng.integers(0, 6, 40).astype(float)
    bad = rng.integers(2, 9, 25).astype(float)
    pairs = [1.0 if b > g else 0.5 if b == g else 0.0 for g, b in itertools.product(good, bad)]
    assert auroc(good, bad) == pytest.approx(float(np.mean(pairs)))


def test_auroc_refuses_empty_or_non_finite_scores() -> None:
    with pytest.raises(ValueError, match="at least one"):
        auroc([], [1.0])
    with pytest.raises(ValueError, match="finite"):
        auroc([1.0, float("nan")], [2.0])


def test_synthetic_parts_are_deterministic_and_extend_without_change() -> None:
    good, bad, masks = synthetic_part("disc", 5, good=3, defects=2)
    again, bad_again, _ = synthetic_part("disc", 5, good=5, defects=4)
    for a, b in zip(good + bad, again[:3] + bad_again[:2], strict=True):
        np.testing.assert_array_equal(a, b)
    later = part_samples("disc", 5, good=2, defects=0, first_good=3)
    assert later is not None
    for a, b in zip(later.good, again[3:], strict=True):
        np.testing.assert_array_equal(a, b)
    other, _, _ = synthetic_part("disc", 6, good=1, defects=0)
    assert not np.array_equal(other[0], good[0])
    assert len(masks) == 2


@pytest.mark.parametrize("name", SYNTHETIC_PARTS)
def test_synthetic_parts_are_colour_images_of_the_asked_size(name: str) -> None:
    samples = part_samples(name, 0, size=160, good=2, defects=len(DEFECTS))
    assert samples is not None
    for image in samples.good + samples.defects:
        assert image.shape == (160, 160, 3)
        assert image.dtype == np.uint8
    assert samples.kinds == list(DEFECTS)
    assert all(m.shape == (160, 160) and m.dtype == np.bool_ for m in samples.masks)


def _check_part(name: str) -> None:
    samples = part_samples(name, 1, good=12, defects=2 * len(DEFECTS))
    assert samples is not None
    side = samples.good[0].shape[0]
    together = zip(samples.defects, samples.clean, samples.masks, samples.kinds, strict=True)
    for defect, clean, mask, kind in together:
        area = int(mask.sum())
        assert area > 0, (name, kind)
        # modest: no defect covers more than 1.5 % of the image (a 0.08-side blob is ~0.5 %)
        assert area < 0.015 * side * side, (name, kind, area)
        diff = np.abs(defect.astype(np.float32) - clean.astype(np.float32))
        if diff.ndim == 3:
            diff = diff.mean(axis=2)
        # visible where it is: a tenth of its pixels changed by 8 grey levels or more (a
        # stain's soft tint: 5); beyond it at most a grey level of a stain's soft tail (8 px
        # out) or of JPEG's 8x8 blocks on the photographs (16 px out)
        least = 5.0 if kind == "stain" else 8.0
        seen = float(np.percentile(diff[mask], 90))
        assert seen >= least, (name, kind, seen)
        reach = 33 if name in PHOTOS else 17
        far = cv2.dilate(mask.astype(np.uint8), np.ones((reach, reach), np.uint8)) == 0
        assert float(diff[far].max()) <= (3.0 if name in PHOTOS else 1.0), (name, kind)
    # the good samples vary (jitter, light, noise), but stay the same part
    a, b = (g.astype(np.float32) for g in samples.good[:2])
    assert 0.5 < float(np.abs(a - b).mean()) < 40.0


@pytest.mark.parametrize("name", SYNTHETIC_PARTS)
def test_synthetic_defects_are_modest_and_visible_in_their_masks(name: str) -> None:
    _check_part(name)


@pytest.mark.parametrize("name", [p.name for p in PHOTO_PARTS])
def test_photograph_defects_are_modest_and_visible_in_their_masks(name: str) -> None:
    if not photo_available():
        pytest.skip(MISSING)
    _check_part(name)


def test_grey_photographs_stay_grey_and_colour_ones_colour() -> None:
    if not photo_available():
        pytest.skip(MISSING)
    brick = part_samples("brick", 0, good=1, defects=1)
    coffee = part_samples("coffee", 0, good=1, defects=1)
    assert brick is not None
    assert coffee is not None
    assert brick.good[0].shape == (224, 224)
    assert coffee.defects[0].shape == (224, 224, 3)


def test_unknown_parts_and_kinds_are_refused() -> None:
    with pytest.raises(ValueError, match="unknown part"):
        part_samples("teapot")
    with pytest.raises(ValueError, match="unknown defect"):
        part_samples("disc", good=0, defects=1, kinds=("dent",))
