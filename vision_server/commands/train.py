"""``vision-server train``: train an anomaly inspection on good images.

    vision-server train INSPECTION --config cell.yaml --images 'good/*.png' [--images ...]
                        [--step NAME] [--method patches|variation] [--false-reject RATE]
                        [--reload] [--json]

Each image is a whole camera image of a good part; the inspection's ROI (a job step's ROI in
its fixture's frame) is cut from it, as the inspection will cut it. The model is written as a
new file ``models/INSPECTION.vN.npz`` beside the configuration, and the configuration's
``model:`` is pointed at it (saved with the file's history, ``vision-server history``). A
running server takes it on ``vision-server reload`` (``--reload`` does that too) or SIGHUP, with
no downtime. Nothing here needs a network.

Exit codes: 0 trained; 2 usage, configuration or images that cannot be trained on (too few,
sizes that differ, unreadable files); 3 the model was written but ``--reload`` could not reach
the server. With ``--json`` the report (or the error) is one JSON object on stdout; with
``--reload`` too, the reload's answer (or its error) is its ``reload``.
"""

from __future__ import annotations

import argparse
import contextlib
import glob
import io
import json
import os
import sys
from collections.abc import Callable
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray

from protocol.cli import CONFIG_ENV, ErrorKind, ExitCode, json_error

from ..analysis import ANOMALY_METHODS, MAX_GOOD_IMAGES_TRAINED, MIN_GOOD_IMAGES, AnomalyError
from ..config import (
    CellConfig,
    ConfigError,
    ModelKeyError,
    history,
    load_config,
    parse_config,
    parse_document,
    set_model_key,
)
from ..service import (
    Trained,
    TrainingError,
    check_usable,
    train_inspection,
    training_patches,
)

MAX_FILES = MAX_GOOD_IMAGES_TRAINED
MAX_FILE_BYTES = 256 << 20

__all__ = ["add_parser", "train_command"]


class TrainUsage(Exception):
    """Training cannot start or failed: ``code`` names why (exit 2)."""

    def __init__(self, code: str, message: str) -> None:
        super().__init__(message)
        self.code = code
        self.message = message


def add_parser(
    sub: Any, parents: list[argparse.ArgumentParser], reload: Callable[[argparse.Namespace], int]
) -> None:
    p = sub.add_parser(
        "train",
        parents=parents,
        help="train an anomaly inspection on good images",
        description="Train INSPECTION (type anomaly, or a job with an anomaly step) on whole "
        "images of good parts: its ROI is cut from each as the inspection cuts it. Writes "
        "models/INSPECTION.vN.npz beside the configuration and points the inspection's "
        "model: at it (recorded in the file's history). Exit 0 trained; 2 usage, "
        "configuration or images; 3 trained but --reload could not reach the server.",
    )
    p.add_argument("inspection", help="the inspection to train")
    p.add_argument(
        "--images",
        action="append",
        required=True,
        metavar="GLOB",
        help="good images: a file or a quoted pattern ('good/*.png'); repeatable",
    )
    p.add_argument("--step", default=None, help="a job's anomaly step (when it has several)")
    p.add_argument(
        "--method", choices=ANOMALY_METHODS, default=None, help="default: the inspection's method:"
    )
    p.add_argument(
        "--false-reject",
        type=float,
        default=None,
        metavar="RATE",
        help="the share of good parts the threshold may fail (default: the inspection's "
        "false_reject:, 0.01)",
    )
    p.add_argument("--reload", action="store_true", help="then ask the running server to reload")
    p.set_defaults(func=lambda args: train_command(args, reload))


def train_command(args: argparse.Namespace, reload: Callable[[argparse.Namespace], int]) -> int:
    json_out = bool(getattr(args, "json", False))
    try:
        trained, path = _train(args, quiet=json_out)
    except TrainUsage as exc:
        if json_out:
            print(json.dumps(json_error(ErrorKind.USAGE, exc.message, exc.code)))
        else:
            print(f"vision-server train: {exc.code}: {exc.message}", file=sys.stderr, flush=True)
        return int(ExitCode.USAGE)
    report = trained.report
    if json_out:
        answer = _report_json(args.inspection, trained, path)
        if args.reload:
            # One JSON object on stdout: the reload's answer (or its error) goes inside it.
            captured = io.StringIO()
            with contextlib.redirect_stdout(captured):
                status = reload(args)
            answer["reload"] = _last_object(captured.getvalue())
            print(json.dumps(answer))
            return 0 if status == 0 else int(ExitCode.CONNECTION)
        print(json.dumps(answer))
    else:
        print(
            f"{args.inspection}: trained {trained.model.method} on {report.images} images in "
            f"{report.seconds:.1f} s; threshold {report.threshold:.4g} for a false-reject rate "
            f"of {report.false_reject:g} ({report.held_out_rejected:.1%} of the held-out good "
            f"images score above it)"
        )
        for line in trained.skipped:
            print(f"  left out: {line}")
        print(f"wrote {trained.path} and set model: {trained.relative} in {path}")
        if not args.reload:
            print("a running server takes it on: vision-server reload (--server HOST:PORT)")
    if args.reload:
        if reload(args) == 0:
            return int(ExitCode.OK)
        print(
            f"the model is written and the configuration points at it; no server took it: "
            f"reload the one that serves {args.config or '$' + CONFIG_ENV} with vision-server "
            "reload --server HOST:PORT (or SIGHUP)",
            file=sys.stderr,
        )
        return int(ExitCode.CONNECTION)
    return int(ExitCode.OK)


def _last_object(text: str) -> Any:
    """The last line of ``text`` that is a JSON object (what a command printed with --json),
    or the text itself when there is none."""
    for line in reversed(text.splitlines()):
        try:
            value = json.loads(line)
        except ValueError:
            continue
        if isinstance(value, dict):
            return value
    return text.strip()


def _report_json(name: str, trained: Trained, path: Path) -> dict[str, Any]:
    report = trained.report
    return {
        "inspection": name,
        "config": str(path),
        "model": trained.relative,
        "method": trained.model.method,
        "version": trained.model.version,
        "images": report.images,
        "threshold": report.threshold,
        "false_reject": report.false_reject,
        "held_out_rejected": report.held_out_rejected,
        "held_out_scores": list(report.held_out_scores),
        "seconds": round(report.seconds, 3),
        "skipped": list(trained.skipped),
    }


def _files(patterns: list[str]) -> list[Path]:
    found: list[Path] = []
    for pattern in patterns:
        matched = sorted(glob.glob(pattern)) or ([pattern] if Path(pattern).exists() else [])
        if not matched:
            raise TrainUsage("NO_IMAGES", f"no file matches {pattern!r}")
        found.extend(Path(m) for m in matched if Path(m).is_file())
    unique = list(dict.fromkeys(found))
    if len(unique) > MAX_FILES:
        raise TrainUsage("TOO_MANY_IMAGES", f"{len(unique)} files: at most {MAX_FILES}")
    return unique


def _read(path: Path) -> NDArray[np.uint8]:
    try:
        size = path.stat().st_size
    except OSError as exc:
        raise TrainUsage("BAD_IMAGE", f"{path}: {exc.strerror}") from None
    if size > MAX_FILE_BYTES:
        raise TrainUsage("BAD_IMAGE", f"{path}: larger than {MAX_FILE_BYTES >> 20} MiB")
    try:
        image = cv2.imread(str(path), cv2.IMREAD_COLOR)
    except cv2.error as exc:  # e.g. more pixels than OpenCV's decoder limit
        reason = str(exc).strip().splitlines()[-1] if str(exc).strip() else "unreadable"
        raise TrainUsage("BAD_IMAGE", f"{path}: OpenCV refused it ({reason})") from None
    if image is None:
        raise TrainUsage("BAD_IMAGE", f"{path}: not an image OpenCV can read")
    return np.asarray(image, np.uint8)


def _train(args: argparse.Namespace, *, quiet: bool) -> tuple[Trained, Path]:
    given = getattr(args, "config", None) or os.environ.get(CONFIG_ENV) or None
    if not given:
        raise TrainUsage("USAGE", f"give --config cell.yaml (or ${CONFIG_ENV})")
    path = Path(given)
    if args.false_reject is not None and not 0.0 < args.false_reject < 0.5:
        raise TrainUsage("USAGE", f"--false-reject must be in (0, 0.5), got {args.false_reject}")
    try:
        old = path.read_bytes()
        config = _config_to_train(path, old, args.inspection, args.step)
    except (ConfigError, OSError) as exc:
        raise TrainUsage("CONFIG_INVALID", f"invalid configuration: {exc}") from None
    inspection = next((i for i in config.inspections if i.name == args.inspection), None)
    if inspection is None:
        known = ", ".join(i.name for i in config.inspections) or "none"
        raise TrainUsage("NOT_FOUND", f"no inspection {args.inspection!r} (inspections: {known})")
    files = _files(args.images)
    if len(files) < MIN_GOOD_IMAGES:
        raise TrainUsage(
            "TOO_FEW_IMAGES", f"{len(files)} images: training needs at least {MIN_GOOD_IMAGES}"
        )
    # Whole images are cut to what the inspection judges as they are read: only the ROIs
    # stay in memory.
    patches: list[NDArray[np.uint8]] = []
    skipped: list[str] = []
    try:
        for file in files:
            cut, left_out = training_patches(inspection, [_read(file)], step=args.step)
            patches.extend(cut)
            skipped.extend(f"{file}: {why.split(': ', 1)[-1]}" for why in left_out)
        check_usable(len(patches), skipped)
    except TrainingError as exc:
        raise TrainUsage("NOT_TRAINABLE", str(exc)) from None
    progress = None if quiet else _progress
    try:
        trained = train_inspection(
            config,
            old.decode("utf-8"),
            args.inspection,
            patches,
            step=args.step,
            method=args.method,
            false_reject=args.false_reject,
            progress=progress,
            cut=True,
        )
    except (TrainingError, AnomalyError, ModelKeyError) as exc:
        raise TrainUsage("NOT_TRAINABLE", str(exc)) from None
    try:
        # The file as it is now (a save made while the training ran is kept), with model: set.
        now = path.read_bytes()
        text = set_model_key(
            now.decode("utf-8"), args.inspection, trained.relative, step=trained.step
        )
        # the new text must load as it will at the next reload or restart
        parse_config(
            parse_document(text, source=str(path)),
            text=text,
            base_dir=path.resolve().parent,
            source=path,
        )
    except (ConfigError, ModelKeyError, OSError, UnicodeError) as exc:
        trained.path.unlink(missing_ok=True)
        raise TrainUsage("NOT_TRAINABLE", f"the configuration with the new model: {exc}") from None
    trained = Trained(**{**trained.__dict__, "text": text})
    try:
        history.write_with_history(
            path,
            trained.text.encode("utf-8"),
            old=now,
            who="vision-server train",
            why=f"trained {trained.relative} on {trained.report.images} images",
        )
    except OSError as exc:
        raise TrainUsage("WRITE_FAILED", f"{path}: {exc}") from None
    return Trained(**{**trained.__dict__, "skipped": tuple(skipped)}), path


RETRAINING = "models/.retraining-{name}.absent.npz"
"""Where the inspection's model is read from while it is retrained: a file that is not there."""


def _config_to_train(path: Path, data: bytes, name: str, step: str | None) -> CellConfig:
    """The configuration, loaded. When it is refused, it is loaded again with the trained
    inspection's ``model:`` pointing at no file: the refusal may be that model's own (an ROI
    resized since, a damaged file: the error says "retrain it"), and training is the cure. Any
    other error is still the first one."""
    try:
        return load_config(path)
    except ConfigError as refused:
        try:
            text = data.decode("utf-8")
            untrained = set_model_key(text, name, RETRAINING.format(name=name), step=step)
            root = parse_document(untrained, source=path.name)
            return parse_config(root, text=text, base_dir=path.resolve().parent, source=path)
        except (ConfigError, ModelKeyError, UnicodeDecodeError):
            raise refused from None


def _progress(message: str) -> None:
    print(f"  {message}", file=sys.stderr, flush=True)
