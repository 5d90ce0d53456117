"""EfficientNet-Lite0 as a feature extractor, run by OpenCV's DNN module.

The network is written out as an ONNX graph with the ``onnx`` package from the state dict of
:mod:`.weights`, batch norms folded into the convolutions, and read by ``cv2.dnn`` (no torch,
no onnxruntime). Lite0 is EfficientNet-B0 without squeeze-and-excitation, with ReLU6 and a fixed
stem and head: 16 inverted-residual blocks in 7 stages. Padding is TensorFlow's "same" (the
weights were trained with it: with symmetric padding the ImageNet top-1 confidence on
scikit-image's cat and coffee photographs drops from 0.79/0.92 to 0.61/0.79).

Only the first 11 blocks run: anomaly detection uses mid-level features (stride 4, 8 and 16),
not the classifier's.
"""

from __future__ import annotations

import hashlib
import threading
from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray

from ..errors import BadImageError
from .weights import WeightsError, read_weights

STRIDE2_BLOCKS = frozenset({1, 3, 5, 11})
"""Blocks whose depthwise convolution halves the resolution."""
TAPS: tuple[int, ...] = (2, 4, 10)
"""The blocks whose outputs are the features: 24 channels at stride 4, 40 at stride 8 and 112
at stride 16."""
TAP_STRIDES: tuple[int, ...] = (4, 8, 16)
BN_EPSILON = 1e-3
INPUT_MULTIPLE = 16
"""Input sides must be multiples of the deepest tap's stride."""
OPSET = 13


def _bn_folded(
    weights: dict[str, NDArray[Any]], conv: str, bn: str
) -> tuple[NDArray[np.float32], NDArray[np.float32]]:
    gamma, beta = weights[bn + ".weight"], weights[bn + ".bias"]
    mean, var = weights[bn + ".running_mean"], weights[bn + ".running_var"]
    scale = gamma / np.sqrt(var + BN_EPSILON)
    kernel = weights[conv] * scale[:, None, None, None]
    return kernel.astype(np.float32), (beta - mean * scale).astype(np.float32)


def build_graph(weights: dict[str, NDArray[Any]], taps: tuple[int, ...] = TAPS) -> bytes:
    """The network up to ``max(taps)`` as a serialised ONNX model with one input ``image``
    (N, 3, H, W) float32 and one output per tap (N, C, H/stride, W/stride)."""
    import onnx
    from onnx import TensorProto, helper, numpy_helper

    nodes: list[Any] = []
    initializers: list[Any] = []

    def constant(name: str, value: NDArray[Any]) -> str:
        initializers.append(numpy_helper.from_array(value.astype(np.float32), name))
        return name

    clip_low = constant("relu6_low", np.array(0.0))
    clip_high = constant("relu6_high", np.array(6.0))

    def conv(source: str, name: str, conv_key: str, bn_key: str, stride: int, act: bool) -> str:
        kernel, bias = _bn_folded(weights, conv_key, bn_key)
        size = kernel.shape[-1]
        groups = kernel.shape[0] if kernel.shape[1] == 1 and size > 1 else 1
        if stride == 2:
            # TensorFlow's "same" on an even side: the extra row and column go after.
            total = size - 2
            pads = [total // 2, total // 2, total - total // 2, total - total // 2]
        else:
            pads = [size // 2] * 4
        out = f"{name}_conv"
        nodes.append(
            helper.make_node(
                "Conv",
                [source, constant(f"{name}_w", kernel), constant(f"{name}_b", bias)],
                [out],
                strides=[stride, stride],
                pads=pads,
                group=groups,
                kernel_shape=[size, size],
            )
        )
        if not act:
            return out
        nodes.append(helper.make_node("Clip", [out, clip_low, clip_high], [f"{name}_relu6"]))
        return f"{name}_relu6"

    x = conv("image", "stem", "_conv_stem.weight", "_bn0", 2, True)
    channels = weights["_conv_stem.weight"].shape[0]
    outputs: list[tuple[str, int]] = []
    for index in range(max(taps) + 1):
        prefix = f"_blocks.{index}."
        block_input, stride = x, 2 if index in STRIDE2_BLOCKS else 1
        if prefix + "_expand_conv.weight" in weights:
            x = conv(
                x, f"b{index}_expand", prefix + "_expand_conv.weight", prefix + "_bn0", 1, True
            )
        x = conv(
            x, f"b{index}_dw", prefix + "_depthwise_conv.weight", prefix + "_bn1", stride, True
        )
        x = conv(x, f"b{index}_project", prefix + "_project_conv.weight", prefix + "_bn2", 1, False)
        out_channels = weights[prefix + "_project_conv.weight"].shape[0]
        if stride == 1 and out_channels == channels:
            nodes.append(helper.make_node("Add", [x, block_input], [f"b{index}_sum"]))
            x = f"b{index}_sum"
        channels = out_channels
        if index in taps:
            outputs.append((x, channels))
    graph = helper.make_graph(
        nodes,
        "efficientnet_lite0_features",
        [helper.make_tensor_value_info("image", TensorProto.FLOAT, [1, 3, None, None])],
        [
            helper.make_tensor_value_info(name, TensorProto.FLOAT, [1, depth, None, None])
            for name, depth in outputs
        ],
        initializers,
    )
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", OPSET)])
    model.ir_version = 8
    onnx.checker.check_model(model)
    return bytes(model.SerializeToString())


@dataclass(frozen=True)
class Features:
    """One image's features: ``maps[i]`` is tap ``i``'s (H/stride, W/stride, C) float32."""

    maps: tuple[NDArray[np.float32], ...]


class Backbone:
    """Lite0's features of images, through cv2.dnn. Thread-safe (one forward at a time per
    instance: cv2.dnn's Net is not re-entrant); build once, it takes about a second."""

    def __init__(self) -> None:
        weights = read_weights()
        graph = build_graph(weights)
        self.digest = hashlib.sha256(graph).hexdigest()
        """Identifies the graph and its weights (what a model file records as its backbone)."""
        self._net = cv2.dnn.readNetFromONNX(np.frombuffer(graph, np.uint8))
        self._outputs = list(self._net.getUnconnectedOutLayersNames())
        self._lock = threading.Lock()

    def features(self, image: NDArray[np.uint8], size: tuple[int, int]) -> Features:
        """The features of ``image`` (BGR or grey uint8) resized to ``size`` (width, height),
        both multiples of 16."""
        blob = _blob(image, size)
        with self._lock:
            self._net.setInput(blob)
            raw = self._net.forward(self._outputs)
        maps = sorted((np.asarray(r)[0].transpose(1, 2, 0) for r in raw), key=lambda m: -m.shape[0])
        return Features(tuple(np.ascontiguousarray(m, dtype=np.float32) for m in maps))


def _blob(image: NDArray[np.uint8], size: tuple[int, int]) -> NDArray[np.float32]:
    if image.dtype != np.uint8 or image.ndim not in (2, 3) or image.size == 0:
        raise BadImageError(f"expected a non-empty uint8 image, got {image.dtype} {image.shape}")
    width, height = size
    if width % INPUT_MULTIPLE or height % INPUT_MULTIPLE:
        raise BadImageError(f"the input size {width}x{height} is not a multiple of 16")
    if image.ndim == 2:
        rgb = cv2.cvtColor(image, cv2.COLOR_GRAY2RGB)
    elif image.shape[2] == 3:
        rgb = cv2.cvtColor(image, cv2.COLOR_BGR2RGB)
    else:
        raise BadImageError(f"expected a grey or BGR image, got {image.shape[2]} channels")
    resized = cv2.resize(rgb, (width, height), interpolation=cv2.INTER_AREA)
    # TensorFlow's EfficientNet-Lite scaling: (x - 127) / 128
    normalised = (resized.astype(np.float32) - 127.0) / 128.0
    return np.ascontiguousarray(normalised.transpose(2, 0, 1)[None])


_shared: Backbone | None = None
_shared_lock = threading.Lock()


def shared_backbone() -> Backbone:
    """One backbone per process (its weights and graph are about 20 MB)."""
    global _shared
    with _shared_lock:
        if _shared is None:
            _shared = Backbone()
        return _shared


__all__ = [
    "Backbone",
    "Features",
    "INPUT_MULTIPLE",
    "TAPS",
    "TAP_STRIDES",
    "WeightsError",
    "build_graph",
    "shared_backbone",
]
