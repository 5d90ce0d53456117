"""A trained anomaly model: its scorer, its threshold and where it came from; training; its file.

The file is a NumPy ``.npz`` archive read with ``allow_pickle=False`` (arrays of numbers only,
never code), holding the scorer's arrays and one ``meta`` array of UTF-8 JSON: the format, the
method, the model's version (counted by whoever trains: the server's ``train`` keeps one file per
version), the input size, the threshold and the false-reject rate it was set for, the held-out
good scores it was set from, each training image's SHA-256 (of its pixels and shape) and, for
``patches``, the backbone's SHA-256 (the ONNX graph with its weights). A model whose backbone
differs from the one installed is refused, not silently scored with other features.
"""

from __future__ import annotations

import hashlib
import io
import json
import math
import os
import time
import tracemalloc
import zipfile
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

import cv2
import numpy as np
from numpy.typing import NDArray

from ..errors import BadImageError
from .backbone import INPUT_MULTIPLE, shared_backbone
from .errors import AnomalyError
from .patches import BANK_MAX, DESCRIPTOR_DIMS, MAX_INPUT, PatchBank, image_score, train_bank
from .threshold import set_threshold
from .variation import VariationModel, train_variation, working_size

Method = Literal["patches", "variation"]
METHODS: tuple[Method, ...] = ("patches", "variation")
FORMAT = "cellvision-anomaly"
FORMAT_VERSION = 1
MIN_IMAGES = 8
"""Fewer good images cannot set a threshold from held-out scores worth the name."""
MAX_IMAGES = 1000
MAX_MODEL_BYTES = 256 << 20
DEFAULT_INPUT = 256
MIN_SIDE = 32
MAX_SIDE = 4096

Array = NDArray[np.float32]


@dataclass(frozen=True)
class AnomalyScore:
    """``score``: how unlike the good images (the model's units; higher is worse);
    ``heat``: float32 (H, W), the same size as the image scored, in the same units."""

    score: float
    heat: Array


@dataclass(frozen=True)
class TrainingReport:
    """What training found: the threshold, the target false-reject rate, the held-out good
    scores (one per image, in the order given), the fraction of them above the threshold,
    seconds and peak traced Python memory in bytes (0: not traced)."""

    threshold: float
    false_reject: float
    held_out_scores: tuple[float, ...]
    held_out_rejected: float
    seconds: float
    peak_bytes: int
    images: int


@dataclass(frozen=True)
class AnomalyModel:
    """A trained model. ``image_size`` (width, height) px: the size of the images it takes;
    ``threshold``: a score above it fails; ``meta``: the file's provenance (see module doc)."""

    method: Method
    image_size: tuple[int, int]
    threshold: float
    false_reject: float
    scorer: PatchBank | VariationModel = field(repr=False)
    meta: dict[str, Any] = field(default_factory=dict, compare=False)

    @property
    def version(self) -> int:
        return int(self.meta.get("version", 1))

    @property
    def digest(self) -> str:
        """Identifies the model: the SHA-256 of its file's content, as written."""
        return str(self.meta.get("digest", ""))

    def score(self, image: NDArray[np.uint8]) -> AnomalyScore:
        """Score one image (uint8 grey or BGR) of the model's ``image_size``."""
        _check_image(image, self.image_size)
        if isinstance(self.scorer, PatchBank):
            bank = self.scorer
            small = bank.heat(bank.cell_distances(bank.grid(shared_backbone(), image)))
            score = image_score(small)
        else:
            small = self.scorer.heat(image)
            score = float(small.max())
        height, width = image.shape[:2]
        heat = np.asarray(cv2.resize(small, (width, height)), np.float32)
        return AnomalyScore(score, heat)


def _check_image(image: NDArray[Any], size: tuple[int, int] | None) -> None:
    if not isinstance(image, np.ndarray) or image.dtype != np.uint8:
        raise BadImageError("expected a uint8 image")
    if image.ndim not in (2, 3) or (image.ndim == 3 and image.shape[2] not in (1, 3)):
        raise BadImageError(f"expected a grey or BGR image, got shape {image.shape}")
    height, width = image.shape[:2]
    if size is not None and (width, height) != size:
        raise BadImageError(
            f"the image is {width}x{height} px, the model was trained on {size[0]}x{size[1]}"
        )


def image_digest(image: NDArray[np.uint8]) -> str:
    """SHA-256 of an image's shape and pixels (what a model records of its training images)."""
    digest = hashlib.sha256(repr(image.shape).encode())
    digest.update(np.ascontiguousarray(image).tobytes())
    return digest.hexdigest()


def input_size(width: int, height: int, side: int = DEFAULT_INPUT) -> tuple[int, int]:
    """The backbone's input for images of ``width`` x ``height``: the longer side ``side`` px,
    aspect kept, both sides rounded to multiples of 16."""
    scale = side / max(width, height)

    def snap(value: float) -> int:
        return max(INPUT_MULTIPLE, int(round(value * scale / INPUT_MULTIPLE)) * INPUT_MULTIPLE)

    return snap(width), snap(height)


def train_model(
    images: Sequence[NDArray[np.uint8]],
    *,
    method: Method = "patches",
    false_reject: float = 0.01,
    seed: int = 0,
    version: int = 1,
    progress: Callable[[str], None] | None = None,
    trace_memory: bool = False,
) -> tuple[AnomalyModel, TrainingReport]:
    """Train on good images (uint8 grey or BGR, all the same size). Raises
    :class:`AnomalyError` for too few or too many images, mixed sizes or a bad rate.
    ``trace_memory``: measure the peak of Python's allocations (tracemalloc slows every thread
    of the process while it runs: for benchmarks, not for a serving process)."""
    if method not in METHODS:
        raise AnomalyError(f"unknown method {method!r} (one of {', '.join(METHODS)})")
    if not 0.0 < false_reject < 0.5:
        raise AnomalyError(f"false_reject {false_reject} is not a rate in (0, 0.5)")
    if len(images) < MIN_IMAGES:
        raise AnomalyError(
            f"{len(images)} good images: training needs at least {MIN_IMAGES} (30 or more "
            "set a steadier threshold)"
        )
    if len(images) > MAX_IMAGES:
        raise AnomalyError(f"{len(images)} images: at most {MAX_IMAGES} are trained on")
    for index, image in enumerate(images):
        try:
            _check_image(image, None)
        except BadImageError as exc:
            raise AnomalyError(f"image {index + 1}: {exc}") from None
    sizes = {(image.shape[1], image.shape[0]) for image in images}
    if len(sizes) > 1:
        listed = ", ".join(f"{w}x{h}" for w, h in sorted(sizes)[:4])
        raise AnomalyError(
            f"the good images differ in size ({listed}): train on crops of one size (one ROI)"
        )
    ((width, height),) = sizes
    if min(width, height) < MIN_SIDE or max(width, height) > MAX_SIDE:
        raise AnomalyError(f"{width}x{height} px: sides must lie in {MIN_SIDE}..{MAX_SIDE} px")
    started = time.perf_counter()
    tracing = trace_memory and not tracemalloc.is_tracing()
    if tracing:
        tracemalloc.start()
    try:
        rng = np.random.default_rng(seed)
        scorer: PatchBank | VariationModel
        meta: dict[str, Any] = {}
        if method == "patches":
            backbone = shared_backbone()
            scorer, held_out = train_bank(
                backbone, images, input_size(width, height), rng, progress
            )
            meta["backbone"] = backbone.digest
        else:
            scorer, held_out = train_variation(images, working_size(width, height))
        peak = tracemalloc.get_traced_memory()[1] if tracing else 0
    finally:
        if tracing:
            tracemalloc.stop()
    threshold = set_threshold(held_out, false_reject)
    rejected = sum(score > threshold for score in held_out) / len(held_out)
    meta.update(
        {
            "version": version,
            "images": [image_digest(image) for image in images],
            "held_out": [round(s, 6) for s in held_out],
            "trained_at": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
        }
    )
    model = AnomalyModel(method, (width, height), threshold, false_reject, scorer, meta)
    report = TrainingReport(
        threshold,
        false_reject,
        tuple(held_out),
        rejected,
        time.perf_counter() - started,
        int(peak),
        len(images),
    )
    return model, report


def model_bytes(model: AnomalyModel) -> bytes:
    """The model's file content."""
    meta = {
        **{k: v for k, v in model.meta.items() if k != "digest"},
        "format": FORMAT,
        "format_version": FORMAT_VERSION,
        "method": model.method,
        "image_size": list(model.image_size),
        "threshold": model.threshold,
        "false_reject": model.false_reject,
    }
    arrays: dict[str, NDArray[Any]] = {
        "meta": np.frombuffer(json.dumps(meta, sort_keys=True).encode("utf-8"), np.uint8)
    }
    if isinstance(model.scorer, PatchBank):
        bank = model.scorer
        arrays.update(
            input_size=np.array(bank.size, np.int32),
            members=bank.members.astype(np.float16),
            scales=bank.scales,
            sources=bank.sources,
        )
    else:
        variation = model.scorer
        arrays.update(
            working_size=np.array(variation.size, np.int32),
            mean=variation.mean,
            spread=variation.spread,
        )
    buffer = io.BytesIO()
    np.savez_compressed(buffer, **arrays)  # type: ignore[arg-type]
    return buffer.getvalue()


def save_model(model: AnomalyModel, path: Path) -> str:
    """Write the model to ``path`` (atomically: a reader sees the old file or the new one);
    returns the file's SHA-256."""
    data = model_bytes(model)
    temporary = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    with open(temporary, "wb") as file:
        file.write(data)
        file.flush()
        os.fsync(file.fileno())
    os.replace(temporary, path)
    return hashlib.sha256(data).hexdigest()


def load_model(path: Path) -> AnomalyModel:
    """Read a model file; raises :class:`AnomalyError` naming what is wrong with it."""
    try:
        size = path.stat().st_size
    except OSError as exc:
        raise AnomalyError(f"cannot read the model {path.name}: {exc.strerror}") from None
    if size > MAX_MODEL_BYTES:
        raise AnomalyError(f"the model {path.name} is larger than {MAX_MODEL_BYTES >> 20} MiB")
    if not path.is_file():
        raise AnomalyError(f"the model {path.name} is not a regular file")
    # read at most the bound: the size seen a moment ago may have grown
    try:
        # non-blocking: a "regular" file whose read blocks (/proc/kmsg) must not hang a reload
        descriptor = os.open(path, os.O_RDONLY | os.O_NONBLOCK)
        with os.fdopen(descriptor, "rb") as stream:
            data = stream.read(MAX_MODEL_BYTES + 1) or b""
    except OSError as exc:
        raise AnomalyError(f"cannot read the model {path.name}: {exc.strerror}") from None
    if len(data) > MAX_MODEL_BYTES:
        raise AnomalyError(f"the model {path.name} is larger than {MAX_MODEL_BYTES >> 20} MiB")
    try:
        return model_from_bytes(data)
    except AnomalyError as exc:
        raise AnomalyError(f"the model {path.name}: {exc}") from None


def _check_unpacked(data: bytes) -> None:
    """Refuse an archive whose arrays would unpack to more than :data:`MAX_MODEL_BYTES` (a
    few kilobytes of compressed zeros can claim gigabytes) before any is unpacked."""
    claims: list[tuple[str, int]] = []
    try:
        with zipfile.ZipFile(io.BytesIO(data)) as archive:
            unpacked = sum(info.file_size for info in archive.infolist())
            # np.load allocates what each array's header claims before reading its data
            for info in archive.infolist():
                with archive.open(info) as member:
                    major, _ = np.lib.format.read_magic(member)
                    read_header = (
                        np.lib.format.read_array_header_1_0
                        if major == 1
                        else np.lib.format.read_array_header_2_0
                    )
                    shape, _, dtype = read_header(member)
                claims.append(
                    (info.filename, int(np.prod(shape, dtype=np.float64)) * dtype.itemsize)
                )
    except (zipfile.BadZipFile, OSError, ValueError, EOFError, TypeError, OverflowError):
        return  # np.load names what is wrong with it
    if unpacked > MAX_MODEL_BYTES:
        raise AnomalyError(
            f"not a cellvision anomaly model (its arrays unpack to {unpacked >> 20} MiB, more "
            f"than {MAX_MODEL_BYTES >> 20} MiB)"
        )
    for name, claimed in claims:
        if claimed > MAX_MODEL_BYTES:
            raise AnomalyError(
                f"not a cellvision anomaly model (array {name} claims {claimed >> 20} MiB)"
            )


def model_from_bytes(data: bytes) -> AnomalyModel:
    """A model from its file's content; raises :class:`AnomalyError`."""
    if not data.startswith(b"PK\x03\x04"):
        raise AnomalyError("not a cellvision anomaly model (not a NumPy .npz archive)")
    _check_unpacked(data)
    try:
        with np.load(io.BytesIO(data), allow_pickle=False) as archive:
            arrays = {name: archive[name] for name in archive.files}
        meta = json.loads(bytes(arrays.pop("meta")).decode("utf-8"))
    except (
        OSError,
        EOFError,  # an empty file: np.load finds no magic number
        ValueError,
        KeyError,
        zipfile.BadZipFile,
        UnicodeDecodeError,
        MemoryError,
        RecursionError,  # a meta of 100,000 nested objects
    ) as exc:
        raise AnomalyError(f"not a cellvision anomaly model ({exc})") from None
    if not isinstance(meta, dict) or meta.get("format") != FORMAT:
        raise AnomalyError("not a cellvision anomaly model")
    if meta.get("format_version") != FORMAT_VERSION:
        raise AnomalyError(
            f"format version {meta.get('format_version')!r}: this server reads {FORMAT_VERSION}"
        )
    try:
        method = meta["method"]
        width, height = (int(v) for v in meta["image_size"])
        threshold = float(meta["threshold"])
        false_reject = float(meta["false_reject"])
        scorer = _scorer(method, arrays, meta)
    except AnomalyError:
        raise
    except (KeyError, TypeError, ValueError, OverflowError) as exc:
        raise AnomalyError(f"a damaged model ({type(exc).__name__}: {exc})") from None
    if not math.isfinite(threshold) or threshold < 0:
        raise AnomalyError(f"a damaged model (threshold {threshold})")
    version = meta.get("version", 1)
    if (
        not (0.0 < false_reject < 0.5)
        or isinstance(version, bool)
        or not isinstance(version, int)
        or not 1 <= version <= 1_000_000
    ):
        raise AnomalyError("a damaged model (false_reject or version)")
    if not (min(width, height) >= MIN_SIDE and max(width, height) <= MAX_SIDE):
        raise AnomalyError(f"a damaged model (image size {width}x{height})")
    meta["digest"] = hashlib.sha256(data).hexdigest()
    return AnomalyModel(method, (width, height), threshold, false_reject, scorer, meta)


def _floats(arrays: dict[str, NDArray[Any]], *names: str) -> None:
    for name in names:
        if arrays[name].dtype.kind != "f":
            raise ValueError(f"{name} is {arrays[name].dtype}, not floating point")


def _scorer(method: str, arrays: dict[str, NDArray[Any]], meta: dict[str, Any]) -> Any:
    if method == "patches":
        installed = shared_backbone().digest
        if meta.get("backbone") != installed:
            raise AnomalyError(
                "it was trained on another backbone than the one installed (retrain it)"
            )
        w, h = (int(v) for v in arrays["input_size"])
        _floats(arrays, "members", "scales")
        members = np.ascontiguousarray(arrays["members"], dtype=np.float32)
        scales = arrays["scales"].astype(np.float32)
        sources = arrays["sources"].astype(np.int32)
        if (
            members.ndim != 2
            or members.shape[1] != DESCRIPTOR_DIMS
            or scales.shape != (3,)
            or sources.shape != members.shape[:1]
            or not 0 < members.shape[0] <= BANK_MAX
        ):
            raise ValueError("bank arrays of the wrong shapes")
        if (
            w % INPUT_MULTIPLE
            or h % INPUT_MULTIPLE
            or not (0 < min(w, h) <= max(w, h) <= MAX_INPUT)
        ):
            raise ValueError(f"input size {w}x{h}")
        if not np.isfinite(members).all() or not (np.isfinite(scales) & (scales > 0)).all():
            raise ValueError("bank members or scales that are not finite and positive")
        return PatchBank((w, h), members, scales, sources)
    if method == "variation":
        w, h = (int(v) for v in arrays["working_size"])
        _floats(arrays, "mean", "spread")
        mean = arrays["mean"].astype(np.float32)
        spread = arrays["spread"].astype(np.float32)
        if not (min(w, h) >= 8 and max(w, h) <= MAX_SIDE):
            raise ValueError(f"working size {w}x{h}")
        if mean.shape != (h, w) or spread.shape != (h, w):
            raise ValueError("mean and spread of the wrong shapes")
        if not np.isfinite(mean).all() or not (np.isfinite(spread) & (spread > 0)).all():
            raise ValueError("a mean that is not finite or spreads not finite and positive")
        return VariationModel((w, h), mean, spread)
    raise ValueError(f"unknown method {method!r}")


__all__ = [
    "MAX_IMAGES",
    "METHODS",
    "MIN_IMAGES",
    "AnomalyError",
    "AnomalyModel",
    "AnomalyScore",
    "Method",
    "TrainingReport",
    "image_digest",
    "load_model",
    "model_bytes",
    "model_from_bytes",
    "save_model",
    "train_model",
]
