"""Training an ``anomaly`` inspection (or a job's ``anomaly`` step) from good images, for
``vision-server train`` and the console.

1. Each good image (a whole camera image) becomes the pixels the inspection judges: its ROI, or
   for a job step the step's ROI in the part frame its fixture finds (the job's earlier steps
   run on the image first). An image whose fixture is not found is left out and named.
2. The model is trained on them (:func:`vision_server.analysis.anomaly.train_model`).
3. The model is written as a new file beside the configuration, never over another:
   ``models/<inspection>[.<step>].v<N>.npz`` with ``N`` one more than the highest there.
4. The configuration's text gets ``model:`` pointing at it (:func:`set_model_key`); the caller
   writes it (with the file's history) and reloads, so that the configuration hash of every
   RESULT names the model, and an undo of that save goes back to the previous model.
"""

from __future__ import annotations

import re
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from ..analysis import (
    AnomalyError,
    AnomalyModel,
    TrainingReport,
    model_bytes,
    train_model,
)
from ..config import CellConfig, files, set_model_key
from ..inspections import AnomalyInspection, Inspection, JobInspection, StepSkipped

MODELS_FOLDER = "models"
MAX_FILE_VERSION = 1_000_000


class TrainingError(ValueError):
    """Training cannot be done as asked (names the inspection, the image or the reason)."""


@dataclass(frozen=True)
class Trained:
    """A finished training: the model, its report, the file written (``relative`` as the
    configuration names it), and the configuration's new text."""

    model: AnomalyModel
    report: TrainingReport
    path: Path
    relative: str
    text: str
    skipped: tuple[str, ...]
    """Images left out, each with the reason (a fixture not found)."""
    step: str | None = None
    """The job's anomaly step trained (None: an anomaly inspection)."""


def _target(inspection: Inspection, step: str | None) -> tuple[Any, Any]:
    """(the anomaly inspection or step, the job when it is a step)."""
    if isinstance(inspection, AnomalyInspection):
        if step is not None:
            raise TrainingError(f"{inspection.name!r} is an anomaly inspection: it has no steps")
        return inspection, None
    if isinstance(inspection, JobInspection):
        anomaly_steps = [s.name for s in inspection.steps if s.type == "anomaly"]
        if step is None:
            if len(anomaly_steps) != 1:
                raise TrainingError(
                    f"job {inspection.name!r} has "
                    f"{len(anomaly_steps) or 'no'} anomaly steps"
                    + (
                        f" ({', '.join(anomaly_steps)}): name one with --step"
                        if anomaly_steps
                        else ""
                    )
                )
            step = anomaly_steps[0]
        for candidate in inspection.steps:
            if candidate.name == step:
                if candidate.type != "anomaly":
                    raise TrainingError(f"step {step!r} is a {candidate.type} step, not anomaly")
                return candidate, inspection
        raise TrainingError(f"job {inspection.name!r} has no step {step!r}")
    raise TrainingError(
        f"{inspection.name!r} is a {inspection.type} inspection: only anomaly inspections and "
        "jobs with an anomaly step are trained"
    )


def training_patches(
    inspection: Inspection, images: Sequence[NDArray[np.uint8]], *, step: str | None = None
) -> tuple[list[NDArray[np.uint8]], list[str]]:
    """The pixels the inspection judges in each whole image, and the images left out (``"image
    N: reason"``, 1-based)."""
    target, job = _target(inspection, step)
    patches: list[NDArray[np.uint8]] = []
    skipped: list[str] = []
    declared = getattr(getattr(inspection, "common", None), "image_size", None)
    where = f"camera {inspection.camera!r} gives"
    for number, image in enumerate(images, 1):
        size = (image.shape[1], image.shape[0])
        if declared is None:
            declared, where = size, "image 1 is"
        if declared is not None and size != tuple(declared):
            raise TrainingError(
                f"image {number} is {size[0]}x{size[1]} px; {where} {declared[0]}x"
                f"{declared[1]}: train on whole images of the inspection's camera, of one size"
            )
        try:
            if job is None:
                patches.append(_roi(image, inspection.common.roi))  # type: ignore[attr-defined]
            else:
                patches.append(_step_patch(job, target, image))
        except (ValueError, LookupError) as exc:
            skipped.append(f"image {number}: {exc}")
    return patches, skipped


def _roi(image: NDArray[np.uint8], roi: tuple[int, int, int, int] | None) -> NDArray[np.uint8]:
    if roi is None:
        return image
    u, v, w, h = roi
    if u + w > image.shape[1] or v + h > image.shape[0]:
        raise ValueError(
            f"the ROI [{u}, {v}, {w}, {h}] reaches past the {image.shape[1]}x{image.shape[0]} image"
        )
    return np.ascontiguousarray(image[v : v + h, u : u + w])


def _step_patch(job: JobInspection, target: Any, image: NDArray[np.uint8]) -> NDArray[np.uint8]:
    outcomes: dict[str, Any] = {}
    for step in job.steps:
        if step is target:
            try:
                return np.ascontiguousarray(step.patch(image, outcomes).image)
            except StepSkipped as exc:
                raise ValueError(str(exc)) from None
        if target.fixture is None:
            continue  # an unfixtured step needs no earlier step
        try:
            outcomes[step.name] = step.run(image, outcomes)
        except StepSkipped as exc:
            raise ValueError(f"step {step.name!r}: {exc}") from None
    raise LookupError("the step is not in the job")


def check_usable(used: int, skipped: Sequence[str]) -> None:
    """Refuse a training where more images were left out than used: that is a fixture that
    does not find the part (or an ROI off the images), not a few bad images to skip."""
    if len(skipped) > used:
        raise TrainingError(
            f"{len(skipped)} of {used + len(skipped)} images could not be used: "
            + "; ".join(skipped[:3])
        )


def next_model_file(base_dir: Path, inspection: str, step: str | None) -> tuple[str, int]:
    """The next free ``models/<name>.v<N>.npz`` (relative to ``base_dir``) and its N."""
    stem = inspection if step is None else f"{inspection}.{step}"
    pattern = re.compile(re.escape(stem) + r"\.v(\d{1,7})\.npz")
    folder = base_dir / MODELS_FOLDER
    highest = 0
    if folder.is_dir():
        for entry in folder.iterdir():
            matched = pattern.fullmatch(entry.name)
            if matched:
                highest = max(highest, int(matched.group(1)))
    version = highest + 1
    if version > MAX_FILE_VERSION:
        raise TrainingError(f"{folder}: {highest} versions of {stem}: remove old ones")
    return f"{MODELS_FOLDER}/{stem}.v{version}.npz", version


def train_inspection(
    config: CellConfig,
    text: str,
    name: str,
    images: Sequence[NDArray[np.uint8]],
    *,
    step: str | None = None,
    method: str | None = None,
    false_reject: float | None = None,
    progress: Callable[[str], None] | None = None,
    cut: bool = False,
) -> Trained:
    """Train ``name`` (of ``config``, whose file's text is ``text``) on good whole images
    (``cut``: on what :func:`training_patches` cut from them already); writes the model file
    and returns the configuration's new text (not written). Raises :class:`TrainingError` (or
    :class:`AnomalyError`) naming the cause."""
    inspection = next((i for i in config.inspections if i.name == name), None)
    if inspection is None:
        known = ", ".join(i.name for i in config.inspections) or "none"
        raise TrainingError(f"no inspection named {name!r} (inspections: {known})")
    target, job = _target(inspection, step)
    settings = target.settings
    patches, skipped = (
        (list(images), []) if cut else training_patches(inspection, images, step=step)
    )
    check_usable(len(patches), skipped)
    step_name = None if job is None else target.name
    relative, version = next_model_file(config.base_dir, name, step_name)
    # refused edits (a flow-style mapping) are found before minutes of training, not after
    set_model_key(text, name, relative, step=step_name)
    model, report = train_model(
        patches,
        method=method or settings.method,  # type: ignore[arg-type]
        false_reject=false_reject if false_reject is not None else settings.false_reject,
        version=version,
        progress=progress,
    )
    new_text = set_model_key(text, name, relative, step=step_name)
    path = config.base_dir / relative
    path.parent.mkdir(parents=True, exist_ok=True)
    # readable as the configuration is (a container's user reads both)
    mode_of = config.source if config.source is not None and config.source.exists() else None
    if not files.write_new(path, model_bytes(model), mode_of=mode_of):
        raise TrainingError(f"{relative} was written meanwhile by another training: train again")
    return Trained(model, report, path, relative, new_text, tuple(skipped), step_name)


__all__ = [
    "MODELS_FOLDER",
    "AnomalyError",
    "Trained",
    "TrainingError",
    "check_usable",
    "next_model_file",
    "train_inspection",
    "training_patches",
]
