"""Anomaly models trained from good images only, on seeded synthetic parts
(tests/helpers/anomaly_synthetic.py): both methods, trained on 20 good parts, score every clear
defect (scratch, hole, stain) above every held-out good part (image AUROC 1.0) and above the
threshold set at training, with the heat map's peak on the defect. The model file round-trips
(same scores) and every damaged or foreign file is refused with an AnomalyError naming why;
training refuses too few images, mixed sizes and images that are not uint8."""

from __future__ import annotations

import hashlib
import io
import json
import math
import zipfile
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from anomaly_synthetic import DEFECTS, auroc, defective_part, dilate, good_part
from hypothesis import given
from hypothesis import strategies as st
from numpy.typing import NDArray

from vision_server.analysis import anomaly as public
from vision_server.analysis.anomaly import (
    MIN_IMAGES,
    AnomalyError,
    AnomalyModel,
    image_digest,
    load_model,
    model_bytes,
    model_from_bytes,
    save_model,
    train_model,
)
from vision_server.analysis.anomaly.backbone import shared_backbone
from vision_server.analysis.anomaly.threshold import set_threshold
from vision_server.analysis.errors import BadImageError

TRAIN = 20
HELD_OUT_GOOD = 10
PER_DEFECT = 3
PEAK_REACH_PX = 16
"""The heat map's maximum must lie within the defect's mask grown by this much."""


class Parts:
    """The seeded data set: training images, held-out good images, defective images with
    their kinds and masks."""

    def __init__(self) -> None:
        rng = np.random.default_rng(31)
        self.train = [good_part(rng) for _ in range(TRAIN)]
        self.good = [good_part(rng) for _ in range(HELD_OUT_GOOD)]
        self.bad = [
            (kind, *defective_part(rng, kind)) for kind in DEFECTS for _ in range(PER_DEFECT)
        ]


@pytest.fixture(scope="module")
def parts() -> Parts:
    return Parts()


@pytest.fixture(scope="module", params=["patches", "variation"])
def trained(request: pytest.FixtureRequest, parts: Parts) -> tuple[AnomalyModel, Any]:
    return train_model(parts.train, method=request.param, false_reject=0.01)


def test_every_clear_defect_scores_above_every_good_part_and_the_threshold(
    trained: tuple[AnomalyModel, Any], parts: Parts
) -> None:
    model, report = trained
    good = [model.score(image).score for image in parts.good]
    bad = {f"{kind} {i}": model.score(image).score for i, (kind, image, _) in enumerate(parts.bad)}
    assert auroc(good, list(bad.values())) == 1.0, (good, bad)
    assert min(bad.values()) > model.threshold, (model.threshold, bad)
    # The threshold is set for 1 % false rejects: the held-out good parts pass.
    assert sum(score > model.threshold for score in good) <= 1, (model.threshold, good)
    assert report.images == TRAIN
    assert len(report.held_out_scores) == TRAIN
    assert report.threshold == model.threshold
    assert report.false_reject == 0.01
    assert 0.0 <= report.held_out_rejected <= 1.0


def test_the_heat_maps_peak_lies_on_the_defect(
    trained: tuple[AnomalyModel, Any], parts: Parts
) -> None:
    model, _ = trained
    for kind, image, mask in parts.bad:
        scored = model.score(image)
        assert scored.heat.shape == image.shape[:2]
        assert scored.heat.dtype == np.float32
        hottest = float(scored.heat.max())
        if model.method == "variation":  # the score is the map's maximum
            assert math.isclose(hottest, scored.score, rel_tol=0.05)
        else:  # the mean of the map's hottest 0.3 %: at most its maximum, near it on a defect
            assert 0.7 * hottest <= scored.score <= hottest * 1.05
        peak = np.unravel_index(int(np.argmax(scored.heat)), scored.heat.shape)
        near = dilate(mask, PEAK_REACH_PX)
        assert near[peak], f"{model.method}: {kind}'s heat peaks at {peak}, off the defect"


def test_the_model_records_its_provenance(trained: tuple[AnomalyModel, Any], parts: Parts) -> None:
    model, _ = trained
    assert model.image_size == (224, 224)
    assert model.version == 1
    assert model.meta["images"] == [image_digest(image) for image in parts.train]
    assert len(model.meta["held_out"]) == TRAIN
    if model.method == "patches":
        assert model.meta["backbone"] == shared_backbone().digest
    else:
        assert "backbone" not in model.meta


def test_the_model_file_round_trips_with_the_same_scores(
    trained: tuple[AnomalyModel, Any], parts: Parts, tmp_path: Path
) -> None:
    model, _ = trained
    path = tmp_path / "m.npz"
    digest = save_model(model, path)
    assert digest == hashlib.sha256(path.read_bytes()).hexdigest()
    loaded = load_model(path)
    assert loaded.digest == digest
    assert (loaded.method, loaded.image_size) == (model.method, model.image_size)
    assert loaded.threshold == model.threshold
    assert loaded.false_reject == model.false_reject
    assert loaded.meta["images"] == model.meta["images"]
    again = model_from_bytes(path.read_bytes())
    for image in [*parts.good[:3], *(b[1] for b in parts.bad[::PER_DEFECT])]:
        first, second = loaded.score(image), again.score(image)
        assert first.score == second.score
        np.testing.assert_array_equal(first.heat, second.heat)
        # patches keeps its bank as float16 in the file: the same scores to within a fraction
        assert math.isclose(first.score, model.score(image).score, rel_tol=0.01)
    # A second save of the loaded model gives a model that scores the same.
    resaved = model_from_bytes(model_bytes(loaded))
    assert resaved.score(parts.good[0]).score == loaded.score(parts.good[0]).score


def test_an_image_of_another_size_is_refused(trained: tuple[AnomalyModel, Any]) -> None:
    model, _ = trained
    with pytest.raises(BadImageError, match="200x224 px, the model was trained on 224x224"):
        model.score(np.zeros((224, 200, 3), np.uint8))
    with pytest.raises(BadImageError, match="uint8"):
        model.score(np.zeros((224, 224, 3), np.float32))  # type: ignore[arg-type]


# --- damaged and foreign files ------------------------------------------------------------


def _arrays(data: bytes) -> dict[str, NDArray[Any]]:
    with np.load(io.BytesIO(data), allow_pickle=False) as archive:
        return {name: archive[name] for name in archive.files}


def _meta(arrays: dict[str, NDArray[Any]]) -> dict[str, Any]:
    meta: dict[str, Any] = json.loads(bytes(arrays["meta"]).decode("utf-8"))
    return meta


def _rewritten(data: bytes, *, allow_pickle: bool = False, **changes: Any) -> bytes:
    """The model file ``data`` with meta keys or arrays replaced (None: removed)."""
    arrays = _arrays(data)
    meta = _meta(arrays)
    for key, value in changes.items():
        if key.startswith("meta_"):
            name = key.removeprefix("meta_")
            if value is None:
                meta.pop(name, None)
            else:
                meta[name] = value
        elif value is None:
            arrays.pop(key)
        else:
            arrays[key] = value
    arrays["meta"] = np.frombuffer(json.dumps(meta).encode("utf-8"), np.uint8)
    buffer = io.BytesIO()
    np.savez(buffer, allow_pickle=allow_pickle, **arrays)
    return buffer.getvalue()


@pytest.fixture(scope="module")
def files(parts: Parts) -> dict[str, bytes]:
    """One file of each method, trained on the minimum of images (what these tests damage)."""
    return {
        method: model_bytes(train_model(parts.train[:MIN_IMAGES], method=method)[0])
        for method in ("patches", "variation")
    }


def test_the_minimal_files_load(files: dict[str, bytes]) -> None:
    for method, data in files.items():
        assert model_from_bytes(data).method == method


@pytest.mark.parametrize(
    ("damage", "cause"),
    [
        (lambda d: d[: len(d) // 2], "not a cellvision anomaly model"),
        (lambda d: b"", "not a cellvision anomaly model"),
        (lambda d: bytes(range(256)) * 40, "not a cellvision anomaly model"),
        (lambda d: b"PK\x03\x04" + b"\x00" * 200, "not a cellvision anomaly model"),
    ],
    ids=["truncated", "empty", "garbage", "broken-zip"],
)
def test_a_truncated_or_garbage_file_is_refused(
    files: dict[str, bytes], damage: Any, cause: str
) -> None:
    with pytest.raises(AnomalyError, match=cause):
        model_from_bytes(damage(files["variation"]))


def test_a_foreign_npz_is_refused(tmp_path: Path) -> None:
    buffer = io.BytesIO()
    np.savez(buffer, weights=np.zeros(10))
    with pytest.raises(AnomalyError, match="not a cellvision anomaly model"):
        model_from_bytes(buffer.getvalue())
    foreign_meta = np.frombuffer(json.dumps({"format": "other"}).encode(), np.uint8)
    buffer = io.BytesIO()
    np.savez(buffer, meta=foreign_meta)
    with pytest.raises(AnomalyError, match="not a cellvision anomaly model"):
        model_from_bytes(buffer.getvalue())
    path = tmp_path / "other.npz"
    path.write_bytes(buffer.getvalue())
    with pytest.raises(AnomalyError, match=r"the model other\.npz: not a cellvision"):
        load_model(path)
    with pytest.raises(AnomalyError, match=r"cannot read the model absent\.npz"):
        load_model(tmp_path / "absent.npz")


def test_a_file_with_pickled_object_arrays_is_refused_without_unpickling(
    files: dict[str, bytes], tmp_path: Path
) -> None:
    witness = tmp_path / "ran"

    class Hostile:
        def __reduce__(self) -> tuple[Any, tuple[str]]:
            import os

            return os.system, (f"touch {witness}",)

    hostile = np.array([Hostile()], dtype=object)
    data = _rewritten(files["variation"], allow_pickle=True, mean=hostile)
    with pytest.raises(AnomalyError, match="not a cellvision anomaly model .*allow_pickle"):
        model_from_bytes(data)
    assert not witness.exists()


def test_another_format_version_is_refused(files: dict[str, bytes]) -> None:
    for version in (2, 0, "1", None):
        data = _rewritten(files["variation"], meta_format_version=version)
        with pytest.raises(AnomalyError, match="format version .*: this server reads 1"):
            model_from_bytes(data)


def test_a_model_of_another_backbone_is_refused(files: dict[str, bytes]) -> None:
    for backbone in ("0" * 64, None):
        data = _rewritten(files["patches"], meta_backbone=backbone)
        with pytest.raises(AnomalyError, match="another backbone than the one installed"):
            model_from_bytes(data)


@pytest.mark.parametrize(
    ("method", "changes", "cause"),
    [
        ("variation", {"meta_method": "magic"}, "unknown method 'magic'"),
        ("variation", {"meta_threshold": -1.0}, "threshold -1.0"),
        ("variation", {"meta_threshold": "NaN"}, "threshold nan"),
        ("variation", {"meta_image_size": None}, "KeyError"),
        ("variation", {"mean": np.zeros((3, 3), np.float32)}, "wrong shapes"),
        ("variation", {"spread": None}, "KeyError"),
        ("patches", {"members": np.zeros((10, 5), np.float16)}, "wrong shapes"),
        ("patches", {"input_size": np.array([100, 224], np.int32)}, "input size 100x224"),
        ("patches", {"input_size": np.array([4096, 224], np.int32)}, "input size 4096x224"),
        # found by an attack: each crashed scoring, loading or a JSON answer
        ("patches", {"input_size": np.array([0, 224], np.int32)}, "input size 0x224"),
        ("patches", {"input_size": np.array([-16, 224], np.int32)}, "input size -16x224"),
        ("patches", {"scales": np.array([1.0, np.nan, 1.0], np.float32)}, "not finite"),
        ("variation", {"mean": "nan-mean"}, "not finite"),
        ("variation", {"spread": "inf-spread"}, "not finite"),
        ("variation", {"mean": "complex-mean"}, "not floating point"),
        ("variation", {"working_size": np.array([0, 0], np.int32)}, "working size 0x0"),
        ("variation", {"meta_version": True}, "false_reject or version"),
        ("variation", {"meta_version": 10**30}, "false_reject or version"),
    ],
    ids=[
        "method",
        "negative-threshold",
        "nan-threshold",
        "no-size",
        "mean-shape",
        "no-spread",
        "bank-shape",
        "input-not-16",
        "input-too-big",
        "input-zero",
        "input-negative",
        "nan-scales",
        "nan-mean",
        "inf-spread",
        "complex-mean",
        "working-zero",
        "bool-version",
        "huge-version",
    ],
)
def test_a_damaged_model_names_what_is_wrong(
    files: dict[str, bytes], method: str, changes: dict[str, Any], cause: str
) -> None:
    arrays = _arrays(files[method])
    for name, value in list(changes.items()):
        if isinstance(value, str) and value in ("nan-mean", "inf-spread"):
            damaged = arrays[name].copy()
            damaged[0, 0] = np.nan if value == "nan-mean" else np.inf
            changes[name] = damaged
        elif isinstance(value, str) and value == "complex-mean":
            changes[name] = arrays[name].astype(np.complex64)
    with pytest.raises(AnomalyError, match=cause):
        model_from_bytes(_rewritten(files[method], **changes))


def test_a_deeply_nested_meta_is_a_damaged_model(files: dict[str, bytes]) -> None:
    arrays = _arrays(files["variation"])
    arrays["meta"] = np.frombuffer(b'{"a":' * 100_000 + b"1" + b"}" * 100_000, np.uint8)
    buffer = io.BytesIO()
    np.savez(buffer, **arrays)
    with pytest.raises(AnomalyError, match="not a cellvision anomaly model"):
        model_from_bytes(buffer.getvalue())


def test_a_non_finite_bank_is_refused(files: dict[str, bytes]) -> None:
    members = _arrays(files["patches"])["members"].copy()
    members[0, 0] = np.inf
    with pytest.raises(AnomalyError, match="not finite"):
        model_from_bytes(_rewritten(files["patches"], members=members))


def test_the_npz_holds_no_pickles(files: dict[str, bytes]) -> None:
    for data in files.values():
        with zipfile.ZipFile(io.BytesIO(data)) as archive:
            for name in archive.namelist():
                header = archive.read(name)[:128]
                assert b"'descr': '|O'" not in header, name


# --- training refusals ------------------------------------------------------------------


def test_training_refuses_too_few_images(parts: Parts) -> None:
    with pytest.raises(AnomalyError, match=f"7 good images: training needs at least {MIN_IMAGES}"):
        train_model(parts.train[: MIN_IMAGES - 1], method="variation")


def test_training_refuses_images_of_mixed_sizes(parts: Parts) -> None:
    images = [*parts.train[:9], parts.train[9][:200, :]]
    with pytest.raises(AnomalyError, match=r"differ in size \(224x200, 224x224\)"):
        train_model(images, method="variation")


@pytest.mark.parametrize(
    ("bad", "cause"),
    [
        (np.zeros((224, 224, 3), np.float32), "image 9: expected a uint8 image"),
        (np.zeros((224, 224, 3), np.uint16), "image 9: expected a uint8 image"),
        (np.zeros((224, 224, 4), np.uint8), "image 9: expected a grey or BGR image"),
        ([[1, 2], [3, 4]], "image 9: expected a uint8 image"),
    ],
    ids=["float32", "uint16", "bgra", "list"],
)
def test_training_refuses_images_that_are_not_uint8_grey_or_bgr(
    parts: Parts, bad: Any, cause: str
) -> None:
    images = [*parts.train[:8], bad]
    with pytest.raises(AnomalyError, match=cause):
        train_model(images, method="variation")


def test_training_refuses_a_bad_method_rate_or_size() -> None:
    images = [np.zeros((64, 64), np.uint8)] * 10
    with pytest.raises(AnomalyError, match="unknown method 'magic'"):
        train_model(images, method="magic")  # type: ignore[arg-type]
    for rate in (0.0, 0.5, -0.1, 1.0):
        with pytest.raises(AnomalyError, match="is not a rate in"):
            train_model(images, method="variation", false_reject=rate)
    with pytest.raises(AnomalyError, match="sides must lie in 32..4096"):
        train_model([np.zeros((16, 64), np.uint8)] * 10, method="variation")


def test_the_public_names_are_exported() -> None:
    for name in public.__all__:
        assert hasattr(public, name), name


# --- the threshold ------------------------------------------------------------------------

scores_lists = st.lists(
    st.floats(min_value=1e-3, max_value=1e3, allow_nan=False), min_size=8, max_size=60
)
rates = st.floats(min_value=0.001, max_value=0.49)


@given(scores_lists, rates)
def test_the_threshold_is_at_least_the_empirical_quantile(scores: list[float], rate: float) -> None:
    threshold = set_threshold(scores, rate)
    assert threshold >= float(np.quantile(scores, 1.0 - rate)) * (1 - 1e-12)
    assert sum(s > threshold for s in scores) / len(scores) <= rate + 1.0 / len(scores)


@given(scores_lists, rates, rates)
def test_a_lower_false_reject_rate_never_lowers_the_threshold(
    scores: list[float], a: float, b: float
) -> None:
    low, high = sorted((a, b))
    assert set_threshold(scores, low) >= set_threshold(scores, high) * (1 - 1e-12)


@given(scores_lists, rates, st.floats(min_value=0.01, max_value=100.0))
def test_the_threshold_scales_with_the_scores(scores: list[float], rate: float, k: float) -> None:
    scaled = set_threshold([s * k for s in scores], rate)
    assert math.isclose(scaled, set_threshold(scores, rate) * k, rel_tol=1e-6)


def test_equal_scores_give_that_score_and_few_spread_scores_reach_past_the_highest() -> None:
    assert math.isclose(set_threshold([2.0] * 20, 0.01), 2.0, rel_tol=1e-9)
    rng = np.random.default_rng(5)
    scores = list(np.exp(rng.normal(0.0, 0.2, 30)))
    # 30 scores cannot show a 1 % tail: the fitted tail lies above the highest seen
    assert set_threshold(scores, 0.01) > max(scores)
    assert set_threshold(scores, 0.2) < max(scores)


def test_an_archive_that_unpacks_too_large_is_refused_before_unpacking(
    files: dict[str, bytes], monkeypatch: pytest.MonkeyPatch
) -> None:
    from vision_server.analysis.anomaly import model as model_module

    monkeypatch.setattr(model_module, "MAX_MODEL_BYTES", 1 << 20)
    assert model_from_bytes(files["variation"]).method == "variation"  # 0.4 MiB unpacked
    arrays = _arrays(files["variation"])
    buffer = io.BytesIO()
    np.savez_compressed(buffer, **arrays, padding=np.zeros(2 << 20, np.uint8))
    assert len(buffer.getvalue()) < 1 << 20
    with pytest.raises(AnomalyError, match="unpack to 2 MiB, more than 1 MiB"):
        model_from_bytes(buffer.getvalue())


def test_an_array_header_claiming_terabytes_is_refused_before_numpy_allocates_it() -> None:
    """Found by a review: np.load trusts a .npy header's shape and allocates it first."""
    header = "{'descr': '<f4', 'fortran_order': False, 'shape': (1000000000000,), }"
    header += " " * (117 - len(header)) + "\n"
    member = b"\x93NUMPY\x01\x00" + len(header).to_bytes(2, "little") + header.encode() + b"\0" * 64
    buffer = io.BytesIO()
    with zipfile.ZipFile(buffer, "w") as archive:
        archive.writestr("members.npy", member)
    with pytest.raises(AnomalyError, match="claims"):
        model_from_bytes(buffer.getvalue())


def test_missing_weights_are_an_anomaly_error_the_train_paths_catch() -> None:
    from vision_server.analysis import WeightsError

    assert issubclass(WeightsError, AnomalyError)
