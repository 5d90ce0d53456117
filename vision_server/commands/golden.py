"""Golden inspection cases: configured inspections checked against known images.

A case is a folder (see test_inspections/README.md)::

    my_case/
      inspection.yaml   # the inspection, in the server configuration's schema
      expected.yaml     # per image: verdict, features, QR text/corners, pose, value (+ tolerances)
      images/           # colour images; NAME.depth0.png, NAME.depth1.png ... are NAME's depth

``inspection.yaml`` is either an inline inspection (and optionally the camera it uses)::

    camera: {source: request, depth: true, intrinsics: {width: 640, ...}}   # optional
    inspection: {name: cap_locate, type: locate, camera: tool, method: circle, ...}

or a reference to an inspection of a cell configuration, so that the file the server runs is
the file under test::

    config: ../../examples/cell.yaml
    inspection: magnet_check
    intrinsics: {width: 640, ...}   # optional: when the configured camera gives none (a
                                    # device's own, e.g. RealSense): those the images had

Both are read with the server configuration's parser (unknown keys are errors; errors name the
file, the line and the key path). ``images: PATH`` points the case at a directory outside the
case (a pool of images shared by several cases); a missing directory is a bad case, unless the
case says ``skip_if_absent: true`` (photographs that are not on every machine): it is then
skipped with the reason.

Green means tested: no case found, a case without images, without ``expected.yaml`` (unless
``--update`` records it) or whose paths do not exist, and a run where every case was skipped
are errors (exit 2) that name the file.

Every image runs through the inspection service, as ``vision-server run`` does
(:func:`vision_server.commands.offline.offline_service`: one worker, the images in the request, the
inspection's camera replaced by a request camera with the same intrinsics).
:func:`run_cases` compares the replies with the expectations and, with
``update=True``, rewrites ``expected.yaml`` from them (keeping tolerances and notes).

:func:`case_from_recording` makes a case from a recording (``vision-server test-inspections
--from-recording DIR --inspection NAME --out CASE``): the recording's frames become the case's
images (copied, lossless; an inspection that takes N frames gets N depth frames per image, as
from the camera), ``inspection.yaml`` references the configuration's inspection, and
``expected.yaml`` records what the inspection gives now, for the integrator to review. The case
copies the frames rather than pointing at the recording, so that it stays a self-contained,
reviewable regression test when the recording is deleted or re-recorded.
"""

from __future__ import annotations

import asyncio
import difflib
import hashlib
import json
import math
import os
import re
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from rich.console import Console
from rich.markup import escape
from rich.table import Table

from protocol import CellvisionError, ImageRole
from yamlfile import boolean, non_negative, non_negative_int, number, one_of, string

from ..cameras import (
    SOURCE_NAMES,
    CameraSettings,
    Intrinsics,
    RecordingError,
    RecordingReader,
    RequestCameraSettings,
)
from ..config import (
    ConfigError,
    Node,
    load_config,
    parse_document,
    read_document,
    settings_from_node,
)
from ..inspections import RESULT_KINDS, Inspection, parse_inspection
from .offline import file_request, image_payload, offline_service

CASE_FILE = "inspection.yaml"
EXPECTED_FILE = "expected.yaml"
COLOR_SUFFIXES = (".png", ".jpg", ".jpeg")
VERDICTS = ("pass", "fail", "error")
TOLERANCE_KEYS = ("tolerance_px", "tolerance_value", "tolerance_m", "tolerance_rad")
RESULT_NAMES = (
    "count",
    "features",
    "angle",
    "failed",
    "steps",
    "text",
    "corners",
    "camera_from_qr",
    "value",
)
"""Every key an expected entry may check, of one type or another."""
TOLERANCE_OF: dict[str, tuple[str, ...]] = {
    "features": ("tolerance_px",),
    "corners": ("tolerance_px",),
    "angle": ("tolerance_rad",),
    "steps": ("tolerance_value",),
    "value": ("tolerance_value",),
    "camera_from_qr": ("tolerance_m", "tolerance_rad"),
}
"""Which tolerance applies to which result: a tolerance that nothing of a type is compared
with is refused for that type (it would be a setting that does nothing)."""
# Which expectation keys each inspection type can have (besides verdict, error, tolerances):
# declared by the type (vision_server.inspections.kinds).
RESULT_KEYS: dict[str, tuple[str, ...]] = {
    kind: results.expected_keys for kind, results in RESULT_KINDS.items()
}
EXIT_OK, EXIT_REGRESSION, EXIT_BAD_CASE = 0, 1, 2


@dataclass(frozen=True)
class Tolerances:
    """How far a result may be from the expectation: pixels (features, corners), the presence
    value, the pose's translation (m) and rotation (rad)."""

    px: float = 1.0
    value: float = 0.02
    m: float = 0.005
    rad: float = 0.01

    def read(self, node: Node, keys: Sequence[str] = TOLERANCE_KEYS) -> Tolerances:
        """These tolerances with those of ``keys`` that ``node`` gives (only ``keys`` are
        taken: the others are unknown keys there)."""
        values = {"px": self.px, "value": self.value, "m": self.m, "rad": self.rad}
        for key in keys:
            field_name = key.removeprefix("tolerance_")
            values[field_name] = node.take(key, non_negative, values[field_name])
        return Tolerances(**values)


def tolerance_keys(kind: str) -> tuple[str, ...]:
    """The tolerances that apply to an inspection type's results, in TOLERANCE_KEYS order."""
    wanted = {t for key in RESULT_KEYS[kind] for t in TOLERANCE_OF.get(key, ())}
    return tuple(key for key in TOLERANCE_KEYS if key in wanted)


@dataclass(frozen=True)
class Expectation:
    """What one image should give. ``None``: not checked."""

    image: str
    verdict: str
    error: str | None = None
    count: int | None = None
    features: tuple[tuple[float, float], ...] | None = None
    text: str | None = None
    corners: tuple[tuple[float, float], ...] | None = None
    camera_from_qr: tuple[tuple[float, ...], ...] | None = None
    value: float | None = None
    angle: float | None = None
    """A job's last part frame's x axis, rad (the summary's ``angle``)."""
    failed: tuple[str, ...] | None = None
    """A job's failed steps (in any order)."""
    steps: dict[str, dict[str, Any]] | None = None
    """A job's step values: numbers within ``tolerance_value``, text and booleans exactly."""
    tolerances: Tolerances = Tolerances()
    raw: dict[str, Any] = field(default_factory=dict)


@dataclass(frozen=True)
class Case:
    """A loaded, valid case."""

    name: str
    directory: Path
    inspection: Inspection
    camera: CameraSettings
    base_dir: Path
    config_hash: str
    images_dir: Path
    # New images in images_dir count: the case's own images/ folder, or a pool (images: PATH)
    # while expected.yaml lists none of it.
    scan: bool
    skip: str | None
    expectations: dict[str, Expectation]
    defaults: dict[str, Any]
    header: str
    expected_text: str


@dataclass(frozen=True)
class Got:
    """What the serving code path answered for one image."""

    verdict: str
    data: dict[str, Any]
    error: str | None = None
    message: str = ""


@dataclass
class ImageReport:
    image: str
    status: str  # pass | regression | new
    expected: str
    got: str
    problems: list[str] = field(default_factory=list)
    result: Got | None = None


@dataclass
class CaseReport:
    name: str
    path: Path
    type: str = ""
    error: str | None = None  # a bad case file
    skipped: str | None = None
    images: list[ImageReport] = field(default_factory=list)
    diff: str = ""


@dataclass
class Report:
    cases: list[CaseReport]
    updated: bool = False
    errors: list[str] = field(default_factory=list)  # not about one case: nothing to test

    def __post_init__(self) -> None:
        if not self.errors and self.cases and all(c.skipped for c in self.cases):
            self.errors.append(
                "nothing was tested: every case was skipped ("
                + "; ".join(f"{c.name}: {c.skipped}" for c in self.cases)
                + ")"
            )

    @property
    def exit_code(self) -> int:
        if self.errors or any(c.error for c in self.cases):
            return EXIT_BAD_CASE
        if not self.updated and any(i.status != "pass" for c in self.cases for i in c.images):
            return EXIT_REGRESSION
        return EXIT_OK

    def counts(self) -> dict[str, int]:
        images = [i for c in self.cases for i in c.images]
        return {
            "cases": len(self.cases),
            "images": len(images),
            "passed": sum(i.status == "pass" for i in images),
            "regressions": sum(i.status == "regression" for i in images),
            "new": sum(i.status == "new" for i in images),
            "skipped_cases": sum(c.skipped is not None for c in self.cases),
            "bad_cases": sum(c.error is not None for c in self.cases),
            "errors": len(self.errors),
        }


# ----------------------------------------------------------------------------- finding cases


def find_cases(paths: Iterable[Path]) -> list[Path]:
    """Case folders under ``paths`` (a case folder, a folder of cases, or an inspection.yaml);
    a path that is none of these, or a folder with no case below it, is returned as it is, to
    be reported as a bad case (a path that tests nothing is an error, never a pass)."""
    found: list[Path] = []
    for path in paths:
        if path.is_file() and path.name == CASE_FILE:
            found.append(path.parent)
        elif (path / CASE_FILE).is_file():
            found.append(path)
        elif path.is_dir():
            below = sorted(p.parent for p in path.rglob(CASE_FILE))
            found.extend(below or [path])
        else:
            found.append(path)
    unique: dict[Path, None] = {}
    for path in found:
        unique.setdefault(path, None)
    return list(unique)


DEFAULT_FOLDER = Path("test_inspections")
"""The cases run without a PATH: this folder of the working directory (never another one: the
cases of the project itself are run by naming them)."""


# ----------------------------------------------------------------------------- loading


def load_case(directory: Path, *, update: bool = False) -> Case:
    """Read and validate a case folder; raises :class:`ConfigError` naming file/line/key.
    Without ``update``, a case must have its ``expected.yaml``."""
    case_file = directory / CASE_FILE
    if not case_file.is_file():
        what = "no such folder" if not directory.exists() else f"no {CASE_FILE} here or below"
        raise ConfigError(
            f"not a case ({what}): a case is a folder with {CASE_FILE}, {EXPECTED_FILE} "
            "and images (see test_inspections/README.md)",
            source=str(directory),
        )
    root, text = read_document(case_file)
    root.source = str(case_file)
    root.take("description", string, None)
    base_dir = directory.resolve()
    inspection, camera, config_base = _inspection(root, base_dir)
    images = root.take("images", string, None)
    skip_if_absent = root.take("skip_if_absent", boolean, False)
    if skip_if_absent and images is None:
        raise root.error("skip_if_absent is for an images: folder outside the case", "images")
    images_dir = base_dir / (images or "images")
    skip = None
    if images is not None and not images_dir.is_dir():
        if not skip_if_absent:
            raise root.error(
                f"no such images directory: {images_dir} (a folder that is not on every "
                "machine needs skip_if_absent: true)",
                "images",
            )
        skip = f"images directory {images_dir} not found"
    root.finish()
    expected_path = directory / EXPECTED_FILE
    if expected_path.is_file():
        exp_root, expected_text = read_document(expected_path)
    elif update or skip is not None:
        expected_text = ""
        exp_root = parse_document("", source=str(expected_path))
    else:
        raise ConfigError(
            f"no {EXPECTED_FILE}: write what each image should give, or record what the "
            "inspection gives now with --update (and check it)",
            source=str(expected_path),
        )
    exp_root.source = str(expected_path)
    defaults_node = exp_root.sub("defaults")
    tolerances = Tolerances().read(defaults_node, tolerance_keys(inspection.type))
    defaults_node.finish()
    expectations: dict[str, Expectation] = {}
    images_node = exp_root.sub("images")
    for key in list(images_node.data):
        if not isinstance(key, str) or not key:
            raise images_node.error(f"image names must be strings, got {key!r}")
        node = images_node.sub(key)
        expectations[key] = _expectation(node, key, inspection, tolerances)
        if skip is None and not (images_dir / key).is_file():
            raise node.error(f"no such image: {images_dir / key}")
    images_node.finish()
    exp_root.finish()
    header = "".join(_leading_comments(expected_text))
    return Case(
        name=_case_name(directory),
        directory=directory,
        inspection=inspection,
        camera=camera,
        base_dir=config_base,
        config_hash=hashlib.sha256(text.encode()).hexdigest()[:16],
        images_dir=images_dir,
        scan=images is None or not expectations,
        skip=skip,
        expectations=expectations,
        defaults=dict(defaults_node.data),
        header=header,
        expected_text=expected_text,
    )


def _case_name(directory: Path) -> str:
    return directory.resolve().name


def _inspection(root: Node, base_dir: Path) -> tuple[Inspection, CameraSettings, Path]:
    if root.has("config"):
        config_path = base_dir / root.take("config", string)
        name = root.take("inspection", string)
        if root.has("camera"):
            raise root.error("with config, the camera comes from the configuration", "camera")
        root.take("camera", string, None)
        intrinsics = None
        if root.has("intrinsics"):
            intrinsics = settings_from_node(root.sub("intrinsics"), Intrinsics)
        else:
            root.take("intrinsics", string, None)  # allowed here, and absent
        if not config_path.is_file():
            raise root.error(f"no such configuration file: {config_path}", "config")
        config = load_config(config_path)
        found = next((i for i in config.inspections if i.name == name), None)
        if found is None:
            names = ", ".join(i.name for i in config.inspections) or "none"
            raise root.error(
                f"{config_path.name} has no inspection {name!r} ({names})", "inspection"
            )
        configured = config.cameras[found.camera]
        if intrinsics is None:
            return found, configured, config.base_dir
        if getattr(configured, "intrinsics", None) is not None:
            raise root.error(
                f"camera {found.camera!r} has intrinsics in {config_path.name}: the case runs "
                "with those; drop intrinsics here",
                "intrinsics",
            )
        # The images' own intrinsics, for a camera whose intrinsics come from its device.
        own: CameraSettings = RequestCameraSettings(intrinsics, depth=found.uses_depth)
        return found, own, config.base_dir
    if root.has("intrinsics"):
        raise root.error("intrinsics go with config (inline: in camera)", "intrinsics")
    root.take("intrinsics", string, None)
    root.take("config", string, None)
    if "inspection" not in root or not isinstance(root.data["inspection"], dict):
        root.sub("inspection", required=True)  # the error: missing, or not a mapping
    camera_name = root.data["inspection"].get("camera")
    camera_name = camera_name if isinstance(camera_name, str) else "camera"
    if root.has("camera"):
        node = root.sub("camera")
        source = node.take("source", one_of(*SOURCE_NAMES), "request")
        camera: CameraSettings = settings_from_node(node, SOURCE_NAMES[source])
    else:
        root.take("camera", string, None)
        camera = RequestCameraSettings(None, depth=True)
    inspection = parse_inspection(
        root.sub("inspection"), base_dir=base_dir, cameras={camera_name: camera}
    )
    return inspection, camera, base_dir


def _points(count: int | None) -> Any:
    def convert(value: Any) -> tuple[tuple[float, float], ...]:
        want = "a list of [u, v]" if count is None else f"a list of {count} [u, v]"
        if not isinstance(value, list) or (count is not None and len(value) != count):
            raise ValueError(f"expected {want}, got {value!r}")
        out = []
        for item in value:
            if not isinstance(item, list) or len(item) != 2:
                raise ValueError(f"expected {want}, got the item {item!r}")
            out.append((number(item[0]), number(item[1])))
        return tuple(out)

    return convert


def _matrix(value: Any) -> tuple[tuple[float, ...], ...]:
    if not isinstance(value, list) or len(value) not in (3, 4):
        raise ValueError(f"expected a 4x4 matrix (rows), got {value!r}")
    rows = []
    for row in value:
        if not isinstance(row, list) or len(row) != 4:
            raise ValueError(f"expected rows of 4 numbers, got {row!r}")
        rows.append(tuple(number(x) for x in row))
    m = np.array(rows[:3])
    if not np.allclose(m[:, :3] @ m[:, :3].T, np.eye(3), atol=1e-4):
        raise ValueError("the rotation part is not orthonormal")
    return tuple(rows)


def _expectation(node: Node, key: str, inspection: Inspection, defaults: Tolerances) -> Expectation:
    kind = inspection.type
    allowed = RESULT_KEYS[kind]
    for other in RESULT_NAMES:
        if other in node and other not in allowed:
            raise node.error(
                f"{other!r} is not a result of a {kind} inspection (a {kind}'s expected entry "
                f"checks: {', '.join(allowed)})",
                other,
            )
    verdict = node.take("verdict", one_of(*VERDICTS))
    node.take("note", string, None)
    error = node.take("error", string, None)
    # Only the type's own keys are taken, so that "allowed here" lists what the type checks.
    given: dict[str, Any] = {}
    readers: dict[str, Any] = {
        "count": non_negative_int,
        "features": _points(None),
        "text": string,
        "corners": _points(4),
        "camera_from_qr": _matrix,
        "value": number,
        "angle": number,
        "failed": _step_list(inspection),
        "steps": _step_values(inspection),
    }
    for name in allowed:
        given[name] = node.take(name, readers[name], None)
    expectation = Expectation(
        image=key,
        verdict=verdict,
        error=error,
        tolerances=defaults.read(node, tolerance_keys(kind)),
        raw=dict(node.data),
        **given,
    )
    if expectation.error is not None and verdict != "error":
        raise node.error("error is only for verdict: error", "error")
    node.finish()
    return expectation


def _declared_steps(inspection: Inspection) -> dict[str, dict[str, str]]:
    """A job's steps and the values each declares, with their types (none for other types)."""
    steps = getattr(inspection, "steps", ())
    return {step.name: dict(step.produces()) for step in steps}


def _step_list(inspection: Inspection) -> Any:
    declared = _declared_steps(inspection)

    def convert(value: Any) -> tuple[str, ...]:
        if not isinstance(value, list) or not all(isinstance(v, str) for v in value):
            raise ValueError(f"expected a list of step names, got {value!r}")
        for name in value:
            if name not in declared:
                raise ValueError(f"no step named {name!r} (the steps are: {', '.join(declared)})")
        return tuple(value)

    return convert


def _step_values(inspection: Inspection) -> Any:
    declared = _declared_steps(inspection)

    def convert(value: Any) -> dict[str, dict[str, Any]]:
        if not isinstance(value, dict):
            raise ValueError(f"expected a mapping of step: {{value: expected}}, got {value!r}")
        out: dict[str, dict[str, Any]] = {}
        for step, values in value.items():
            if step not in declared:
                raise ValueError(f"no step named {step!r} (the steps are: {', '.join(declared)})")
            if not isinstance(values, dict) or not values:
                raise ValueError(f"step {step!r}: expected a mapping of value: expected")
            for name, want in values.items():
                if name not in declared[step]:
                    offered = ", ".join(declared[step])
                    raise ValueError(f"step {step!r} has no value {name!r} (it has: {offered})")
                wanted_type = declared[step][name]
                ok = want is None or (  # None: not measured
                    isinstance(want, bool)
                    if wanted_type == "bool"
                    else isinstance(want, str)
                    if wanted_type == "text"
                    else isinstance(want, int | float) and not isinstance(want, bool)
                )
                if not ok:
                    raise ValueError(f"{step}.{name} is a {wanted_type} value, got {want!r}")
            out[str(step)] = dict(values)
        return out

    return convert


def _leading_comments(text: str) -> list[str]:
    out = []
    for line in text.splitlines(keepends=True):
        if not line.startswith("#"):
            break
        out.append(line)
    return out


# ----------------------------------------------------------------------------- running


def color_images(case: Case) -> list[str]:
    """The case's images: those with expectations, then new colour images in its own images/
    folder (a folder named by ``images:`` is a pool the case picks from; while it has picked
    none, every image of the pool is new)."""
    names = list(case.expectations)
    if case.scan and case.images_dir.is_dir():
        for path in sorted(case.images_dir.iterdir()):
            if (
                path.suffix.lower() in COLOR_SUFFIXES
                and ".depth" not in path.name
                and path.name not in case.expectations
            ):
                names.append(path.name)
    return names


def depth_frames(color: Path) -> list[Path]:
    """NAME.depth.png, NAME.depth0.png, NAME.depth1.png ... beside NAME.png."""
    return sorted(color.parent.glob(f"{color.stem}.depth*.png"), key=_natural)


def _natural(path: Path) -> list[Any]:
    return [int(t) if t.isdigit() else t for t in re.split(r"(\d+)", path.name)]


def run_images(case: Case, names: Sequence[str]) -> list[Got]:
    """Run the case's inspection on each image through the inspection service."""
    service = offline_service(
        case.inspection, case.camera, case.base_dir, config_hash=case.config_hash
    )

    async def run_all() -> list[Got]:
        out = []
        try:
            for index, name in enumerate(names, start=1):
                color = case.images_dir / name
                depth = []
                if case.inspection.uses_depth:
                    depth = [image_payload(p, ImageRole.DEPTH) for p in depth_frames(color)]
                request = file_request(
                    case.inspection.name,
                    image_payload(color, ImageRole.COLOR),
                    depth,
                    peer="golden",
                    request_id=index,
                )
                try:
                    reply = await service.inspect(request)
                except CellvisionError as exc:
                    out.append(Got("error", {}, exc.code.name, exc.message))
                    continue
                out.append(Got("pass" if reply.passed else "fail", dict(reply.data)))
        finally:
            service.close()
        return out

    return asyncio.run(run_all())


def compare(expected: Expectation, got: Got) -> list[str]:
    """What differs, as sentences (empty: the image passes)."""
    problems = []
    tol = expected.tolerances
    if got.verdict != expected.verdict:
        extra = f" ({got.error}: {got.message})" if got.error else ""
        problems.append(f"verdict {got.verdict}, expected {expected.verdict}{extra}")
    if expected.error is not None and got.error != expected.error:
        problems.append(f"error {got.error}, expected {expected.error}")
    if got.error is not None:
        return problems
    data = got.data
    if expected.count is not None and data.get("count") != expected.count:
        problems.append(f"count {data.get('count')}, expected {expected.count}")
    if expected.features is not None:
        found = [(float(f["u"]), float(f["v"])) for f in data.get("features", [])]
        problems += _match_features(expected.features, found, tol.px)
    if expected.text is not None and data.get("text") != expected.text:
        problems.append(f"text {data.get('text')!r}, expected {expected.text!r}")
    if expected.corners is not None:
        corners = data.get("corners")
        if not corners:
            problems.append("no corners, expected 4")
        else:
            errors = np.hypot(*(np.asarray(corners) - np.asarray(expected.corners)).T)
            worst = int(np.argmax(errors))
            if errors[worst] > tol.px:
                problems.append(
                    f"corner c{worst} off by {errors[worst]:.2f} px (tolerance {tol.px} px)"
                )
    if expected.camera_from_qr is not None:
        pose = data.get("camera_from_qr")
        if pose is None:
            problems.append("no pose, expected camera_from_qr")
        else:
            dt, dr = pose_error(np.asarray(expected.camera_from_qr), np.asarray(pose))
            if dt > tol.m:
                problems.append(f"translation off by {dt * 1000:.2f} mm (tolerance {tol.m} m)")
            if dr > tol.rad:
                problems.append(f"rotation off by {dr:.4f} rad (tolerance {tol.rad} rad)")
    if expected.value is not None:
        value = data.get("value")
        if value is None or abs(float(value) - expected.value) > tol.value:
            problems.append(_value_problem(value, expected.value, tol.value, data))
    problems += _compare_job(expected, data)
    return problems


def _value_problem(value: Any, expected: float, tolerance: float, data: dict[str, Any]) -> str:
    """A value out of tolerance as a person reads it: rounded, in its unit (a caliper's mm or
    px, its first measurement's) or with what it measures (a presence's ``dark_fraction``)."""
    measurements = data.get("measurements") or []
    unit = measurements[0].get("unit") if measurements else data.get("units")
    got = _readable(value, 4)
    if unit:
        return f"value {got} {unit}, expected {expected} ± {tolerance} {unit}"
    measure = data.get("measure")
    return f"value {got}, expected {expected} ± {tolerance}" + (f" ({measure})" if measure else "")


def _compare_job(expected: Expectation, data: dict[str, Any]) -> list[str]:
    """A job's angle, failed steps and step values."""
    problems = []
    tol = expected.tolerances
    if expected.angle is not None:
        frames = data.get("features") or []
        angle = frames[-1].get("angle") if frames else None
        if angle is None:
            problems.append(f"no part frame, expected angle {expected.angle} rad")
        elif abs(_angle_difference(float(angle), expected.angle)) > tol.rad:
            problems.append(
                f"angle {float(angle):.4f} rad, expected {expected.angle} ± {tol.rad} rad"
            )
    if expected.failed is not None:
        failed = list(data.get("failed") or [])
        if sorted(failed) != sorted(expected.failed):
            shown = ", ".join(failed) or "none"
            problems.append(
                f"failed steps: {shown}; expected: {', '.join(expected.failed) or 'none'}"
            )
    for step, values in (expected.steps or {}).items():
        got = (data.get("steps") or {}).get(step, {})
        for name, want in values.items():
            value = got.get(name)
            if isinstance(want, int | float) and not isinstance(want, bool):
                if value is None or abs(float(value) - want) > tol.value:
                    problems.append(
                        f"{step}.{name} {_readable(value)}, expected {want} ± {tol.value}"
                    )
            elif value != want:
                problems.append(f"{step}.{name} {value!r}, expected {want!r}")
    return problems


def _angle_difference(a: float, b: float) -> float:
    """a - b wrapped to [-pi, pi) (rad)."""
    return (a - b + math.pi) % (2.0 * math.pi) - math.pi


def _readable(value: Any, places: int = 3) -> str:
    """A measured number as a person reads it (at most ``places`` decimals, no ``-0.0``);
    None: 'not measured'."""
    if value is None:
        return "not measured"
    return repr(round(float(value), places) + 0.0)


def pose_error(expected: Any, got: Any) -> tuple[float, float]:
    """Translation distance (m) and rotation angle (rad) between two 4x4 poses."""
    dt = float(np.linalg.norm(got[:3, 3] - expected[:3, 3]))
    relative = expected[:3, :3].T @ got[:3, :3]
    cos = float(np.clip((np.trace(relative) - 1.0) / 2.0, -1.0, 1.0))
    return dt, math.acos(cos)


def _match_features(
    expected: Sequence[tuple[float, float]], found: Sequence[tuple[float, float]], tol: float
) -> list[str]:
    """Each expected feature must be matched by its own found feature within ``tol`` px
    (closest pairs first)."""
    pairs = sorted(
        (math.hypot(e[0] - f[0], e[1] - f[1]), i, j)
        for i, e in enumerate(expected)
        for j, f in enumerate(found)
    )
    matched: dict[int, float] = {}
    used: set[int] = set()
    for distance, i, j in pairs:
        if distance > tol:
            break
        if i not in matched and j not in used:
            matched[i] = distance
            used.add(j)
    problems = []
    for i, (u, v) in enumerate(expected):
        if i in matched:
            continue
        nearest = min((math.hypot(u - f[0], v - f[1]) for f in found), default=math.inf)
        near = "none found" if math.isinf(nearest) else f"nearest {nearest:.2f} px"
        problems.append(f"feature ({u:.1f}, {v:.1f}) not found within {tol} px ({near})")
    return problems


def describe_expected(e: Expectation) -> str:
    parts = [e.verdict + (f" {e.error}" if e.error else "")]
    if e.count is not None:
        parts.append(f"{e.count} found")
    if e.features is not None:
        parts.append(f"{len(e.features)} features ±{e.tolerances.px} px")
    if e.text is not None:
        parts.append(_short(e.text))
    if e.corners is not None:
        parts.append(f"corners ±{e.tolerances.px} px")
    if e.camera_from_qr is not None:
        t = np.asarray(e.camera_from_qr)[:3, 3]
        parts.append(f"t=({t[0]:.3f}, {t[1]:.3f}, {t[2]:.3f}) m ±{e.tolerances.m} m")
    if e.value is not None:
        parts.append(f"value {e.value:.3f} ±{e.tolerances.value}")
    if e.angle is not None:
        parts.append(f"angle {e.angle:.4f} ±{e.tolerances.rad} rad")
    if e.failed is not None:
        parts.append("failed: " + (", ".join(e.failed) or "none"))
    for step, values in (e.steps or {}).items():
        parts += [f"{step}.{name} {want}" for name, want in values.items()]
    return ", ".join(parts)


def _short(text: str, limit: int = 32) -> str:
    return repr(text if len(text) <= limit else text[: limit - 1] + "…")


def describe_got(got: Got) -> str:
    if got.error:
        return f"error {got.error}"
    data = got.data
    parts = [got.verdict]
    if "count" in data:
        parts.append(f"{data['count']} found")
    if data.get("text") is not None:
        parts.append(_short(str(data["text"])))
    if data.get("camera_from_qr") is not None:
        t = np.asarray(data["camera_from_qr"])[:3, 3]
        parts.append(f"t=({t[0]:.3f}, {t[1]:.3f}, {t[2]:.3f}) m")
    if data.get("value") is not None:
        parts.append(f"value {float(data['value']):.3f}")
    if data.get("found") is False:
        parts.append("nothing found")
    if isinstance(data.get("failed"), list):  # a job's failed steps
        parts.append("failed: " + (", ".join(data["failed"]) or "none"))
    return ", ".join(parts)


def run_case(directory: Path, *, update: bool = False) -> CaseReport:
    """Load one case, run every image, compare; with ``update`` rewrite expected.yaml."""
    report = CaseReport(_case_name(directory), directory)
    try:
        case = load_case(directory, update=update)
        report.type = case.inspection.type
        if case.skip is not None:
            report.skipped = case.skip
            return report
        names = color_images(case)
        if not names:
            raise ConfigError(
                f"no images to test: {case.images_dir} "
                + ("has no " if case.images_dir.is_dir() else "does not exist (nor any ")
                + "/".join(COLOR_SUFFIXES)
                + (" images" if case.images_dir.is_dir() else " images)"),
                source=str(directory / CASE_FILE),
            )
        results = run_images(case, names)
    except ConfigError as exc:
        report.error = str(exc)
        return report
    except ValueError as exc:  # an unreadable image
        report.error = f"{directory}: {exc}"
        return report
    for name, got in zip(names, results, strict=True):
        expectation = case.expectations.get(name)
        if expectation is None:
            report.images.append(
                ImageReport(
                    name, "new", "—", describe_got(got), ["no expected result (--update)"], got
                )
            )
            continue
        problems = compare(expectation, got)
        report.images.append(
            ImageReport(
                name,
                "pass" if not problems else "regression",
                describe_expected(expectation),
                describe_got(got),
                problems,
                got,
            )
        )
    if update:
        new_text = expected_yaml(
            case.header or DEFAULT_HEADER,
            case.defaults,
            {
                i.image: updated_entry(case.expectations.get(i.image), i.result, case)
                for i in report.images
                if i.result is not None
            },
        )
        if new_text != case.expected_text:
            path = directory / EXPECTED_FILE
            report.diff = "".join(
                difflib.unified_diff(
                    case.expected_text.splitlines(keepends=True),
                    new_text.splitlines(keepends=True),
                    f"{path} (before)",
                    f"{path} (updated)",
                )
            )
            path.write_text(new_text, encoding="utf-8")
    return report


def run_cases(paths: Sequence[Path] | None = None, *, update: bool = False) -> Report:
    """Run the cases under ``paths`` (none given: ./test_inspections, which must exist)."""
    if not paths:
        if not DEFAULT_FOLDER.is_dir():
            where = DEFAULT_FOLDER.resolve()
            return Report(
                [],
                updated=update,
                errors=[
                    f"{where}: no such folder; run in a folder that has test_inspections/, "
                    "or name the cases: vision-server test-inspections PATH ..."
                ],
            )
        paths = [DEFAULT_FOLDER]
    cases = find_cases(paths)
    return Report([run_case(path, update=update) for path in cases], updated=update)


# ----------------------------------------------------------------------------- updating

DEFAULT_HEADER = (
    "# Expected results of this case's inspection, per image (see test_inspections/README.md).\n"
    "# `vision-server test-inspections --update` rewrites it and keeps tolerances and notes.\n"
)


def updated_entry(old: Expectation | None, got: Got, case: Case) -> dict[str, Any]:
    """The expectation an updated file holds for ``got``: an old entry keeps its keys (the
    checks it had), tolerances and note; a new one gets every result of its type."""
    fresh = result_entry(got, case.inspection.type)
    if old is None:
        return fresh
    out: dict[str, Any] = {"verdict": fresh["verdict"]}
    if "error" in fresh:
        out["error"] = fresh["error"]
    for key in RESULT_KEYS[case.inspection.type]:
        if key == "steps" and key in old.raw:
            # the same step values as before, measured again
            steps = got.data.get("steps") or {}
            out[key] = {
                step: {name: _recorded(steps.get(step, {}).get(name)) for name in values}
                for step, values in (old.steps or {}).items()
            }
        elif key in old.raw and key in fresh:
            out[key] = fresh[key]
    for key in ("note", *TOLERANCE_KEYS):
        if key in old.raw:
            out[key] = old.raw[key]
    return out


def result_entry(got: Got, kind: str) -> dict[str, Any]:
    """The expected entry for ``got``: its verdict, and the error or the type's own entry."""
    out: dict[str, Any] = {"verdict": got.verdict}
    if got.error is not None:
        out["error"] = got.error
        return out
    return {**out, **RESULT_KINDS[kind].expected(got.data)}


def _recorded(value: Any) -> Any:
    """A step value as an expected.yaml records it (numbers to 4 decimals)."""
    if isinstance(value, float):
        return round(value, 4) + 0.0
    return value


_PLAIN = re.compile(r"[A-Za-z0-9_][A-Za-z0-9_./-]*")


def _scalar(value: Any) -> str:
    if isinstance(value, str):
        if _PLAIN.fullmatch(value) and value.lower() not in ("true", "false", "null", "yes", "no"):
            try:
                float(value)
            except ValueError:
                return value
        return json.dumps(value, ensure_ascii=False)
    if value is None:
        return "null"
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, float) and value == int(value) and abs(value) < 1e15:
        return f"{value:.1f}"
    if isinstance(value, list):
        return "[" + ", ".join(_scalar(v) for v in value) + "]"
    if isinstance(value, dict):
        return "{" + ", ".join(f"{_scalar(k)}: {_scalar(v)}" for k, v in value.items()) + "}"
    return _yaml_float(value) if isinstance(value, float) else str(value)


def _yaml_float(value: float) -> str:
    """A float as YAML 1.1 (PyYAML) reads it back as a float: ``-4e-05`` would be a string,
    ``-4.0e-05`` is a number."""
    text = repr(value)
    mantissa, e, exponent = text.partition("e")
    if e and "." not in mantissa:
        return f"{mantissa}.0e{exponent}"
    return text


def expected_yaml(header: str, defaults: dict[str, Any], entries: dict[str, dict[str, Any]]) -> str:
    """The text of an expected.yaml: lists of points one per line, numbers as given."""
    lines = [header.rstrip("\n")] if header.strip() else []
    if defaults:
        lines.append("defaults:")
        lines += [f"  {k}: {_scalar(v)}" for k, v in defaults.items()]
    lines.append("images:" if entries else "images: {}")
    for name, entry in entries.items():
        lines.append(f"  {_scalar(name)}:")
        for key, value in entry.items():
            if isinstance(value, list) and value and isinstance(value[0], list):
                lines.append(f"    {key}:")
                lines += [f"      - {_scalar(item)}" for item in value]
            else:
                lines.append(f"    {key}: {_scalar(value)}")
    return "\n".join(lines) + "\n"


# ----------------------------------------------------------------------------- reporting


def report_json(report: Report) -> dict[str, Any]:
    return {
        "ok": report.exit_code == EXIT_OK,
        "exit_code": report.exit_code,
        "updated": report.updated,
        "errors": report.errors,
        "summary": report.counts(),
        "cases": [
            {
                "case": c.name,
                "path": str(c.path),
                "type": c.type,
                "error": c.error,
                "skipped": c.skipped,
                "diff": c.diff or None,
                "images": [
                    {
                        "image": i.image,
                        "status": i.status,
                        "expected": i.expected,
                        "got": i.got,
                        "problems": i.problems,
                        "verdict": None if i.result is None else i.result.verdict,
                        "data": None if i.result is None else i.result.data,
                    }
                    for i in c.images
                ],
            }
            for c in report.cases
        ],
    }


def print_report(report: Report, console: Console) -> None:
    if report.cases:
        _print_table(report, console)
    for error in report.errors:
        console.print(f"[red]error:[/] {escape(error)}", highlight=False)
    for case in report.cases:
        if case.error is not None:
            console.print(
                f"[red]bad case {escape(case.name)}:[/] {escape(case.error)}", highlight=False
            )
        if case.diff:
            console.print(f"[bold]{escape(case.name)}: expected.yaml updated[/]")
            for line in case.diff.splitlines():
                style = "green" if line.startswith("+") else "red" if line.startswith("-") else ""
                console.print(line, style=style or None, highlight=False, markup=False)
    n = report.counts()
    summary = (
        f"{_count(n['cases'], 'case')}, {_count(n['images'], 'image')}: {n['passed']} passed, "
        f"{_count(n['regressions'], 'regression')}, {n['new']} new, "
        f"{_count(n['skipped_cases'], 'case')} skipped, {_count(n['bad_cases'], 'bad case')}"
    )
    if report.updated:
        changed = sum(bool(c.diff) for c in report.cases)
        summary += f"; expected.yaml rewritten in {_count(changed, 'case')}"
    console.print(summary, highlight=False)


def _print_table(report: Report, console: Console) -> None:
    table = Table(title="test-inspections" + (" (--update)" if report.updated else ""))
    for column in ("case", "image", "expected", "got", "pass"):
        table.add_column(column, overflow="fold")
    for case in report.cases:
        if case.error is not None:
            table.add_row(escape(case.name), "—", "—", "—", "[red]BAD CASE[/]")
            continue
        if case.skipped is not None:
            table.add_row(
                escape(case.name), "—", "—", "—", f"[yellow]skipped[/]: {escape(case.skipped)}"
            )
            continue
        for image in case.images:
            mark = {
                "pass": "[green]✓[/]",
                "regression": "[red]✗ " + escape("; ".join(image.problems)) + "[/]",
                "new": "[yellow]new[/]: no expected result",
            }[image.status]
            cells = (case.name, image.image, image.expected, image.got)
            table.add_row(*(escape(cell) for cell in cells), mark)
    console.print(table)


def _count(n: int, noun: str) -> str:
    return f"{n} {noun}" + ("" if n == 1 else "s")


# ----------------------------------------------------------------------------- from a recording


def case_from_recording(
    recording_dir: Path,
    config_path: Path,
    inspection_name: str,
    out: Path,
    *,
    frames: Sequence[int] = (),
) -> CaseReport:
    """Make the case ``out`` from a recording: its frames (those from ``frames``, default all)
    as images, the configuration's inspection, and ``expected.yaml`` from what the inspection
    gives now (:func:`run_case` with ``update``). Raises ``ConfigError`` for a bad
    configuration, inspection, recording, frame or ``out`` (nothing written then)."""
    config = load_config(config_path)
    inspection = next((i for i in config.inspections if i.name == inspection_name), None)
    if inspection is None:
        names = ", ".join(i.name for i in config.inspections) or "none"
        raise ConfigError(
            f"no inspection {inspection_name!r} (configured: {names})", source=str(config_path)
        )
    try:
        recording = RecordingReader(recording_dir)
    except RecordingError as exc:
        raise ConfigError(str(exc), source=str(recording_dir)) from None
    group = max(1, inspection.frames)
    total = len(recording)
    starts = list(frames) or list(range(0, total - group + 1, group))
    bad = [start for start in starts if not 0 <= start <= total - group]
    if bad or not starts:
        raise ConfigError(
            f"the recording has {total} frames (0..{total - 1}) and {inspection.name} takes "
            f"{group} at a time: "
            + (f"no run from frame {bad[0]}" if bad else "not enough for one"),
            source=str(recording_dir),
        )
    if out.exists() and (not out.is_dir() or any(out.iterdir())):
        raise ConfigError("already exists: a case is made in a new folder", source=str(out))
    configured = config.cameras[inspection.camera]
    intrinsics = None
    if getattr(configured, "intrinsics", None) is None and recording.intrinsics is not None:
        intrinsics = recording.intrinsics
    images = out / "images"
    try:
        images.mkdir(parents=True, exist_ok=True)
        for start in starts:
            _copy_run(recording, start, group, images, depth=inspection.uses_depth)
    except RecordingError as exc:
        raise ConfigError(str(exc), source=str(recording_dir)) from None
    except OSError as exc:
        raise ConfigError(f"cannot write: {exc.strerror or exc}", source=str(images)) from None
    relative = Path(_relative(config_path.resolve(), out.resolve()))
    lines = [
        f"# Made by `vision-server test-inspections --from-recording` from {recording_dir}",
        f"# (camera {recording.camera}, {recording.source}; recorded {recording.started};",
        f"# configuration hash then {recording.config_hash or 'unknown'}). expected.yaml holds",
        "# what the inspection gave on these frames when the case was made: review it.",
        f"description: {json.dumps(f'frames of the recording {recording_dir.name}')}",
        f"config: {json.dumps(relative.as_posix())}",
        f"inspection: {json.dumps(inspection.name)}",
    ]
    if intrinsics is not None:
        values = {
            "width": intrinsics.width,
            "height": intrinsics.height,
            "fx": intrinsics.fx,
            "fy": intrinsics.fy,
            "cx": intrinsics.cx,
            "cy": intrinsics.cy,
            "distortion": list(intrinsics.distortion),
        }
        lines.append("# The recording's intrinsics: the configured camera gives none.")
        lines.append(f"intrinsics: {json.dumps(values)}")
    (out / CASE_FILE).write_text("\n".join(lines) + "\n", encoding="utf-8")
    return run_case(out, update=True)


def _relative(target: Path, start: Path) -> str:
    return os.path.relpath(target, start)


def _copy_run(
    recording: RecordingReader, start: int, group: int, images: Path, *, depth: bool
) -> None:
    """One run's frames into a case's images: the first frame's colour as frame_NNNNNN.png
    (an 8-bit file copied as it is, 16-bit gray scaled as the camera gives it), the depth of
    each as frame_NNNNNN.depth0.png, .depth1.png, ..."""
    first = recording.read(start)
    name = f"frame_{start:06d}"
    if first.color.dtype == np.uint8:
        data = (recording.path / first.entry.color).read_bytes()
    else:
        ok, encoded = cv2.imencode(".png", first.color8())
        if not ok:  # pragma: no cover - an 8-bit array always encodes
            raise RecordingError(f"cannot encode frame {start} as PNG")
        data = bytes(encoded)
    (images / f"{name}.png").write_bytes(data)
    if not depth:
        return
    for j, index in enumerate(range(start, start + group)):
        entry = recording.read(index).entry if index != start else first.entry
        if entry.depth is None:
            continue
        data = (recording.path / entry.depth).read_bytes()
        (images / f"{name}.depth{j}.png").write_bytes(data)


def golden_command(paths: Sequence[str], *, json_out: bool = False, update: bool = False) -> int:
    """``vision-server test-inspections``: 0 all pass, 1 a regression, 2 a bad case file."""
    report = run_cases([Path(p) for p in paths] or None, update=update)
    if json_out:
        print(json.dumps(report_json(report)))
    else:
        print_report(report, Console())
    return report.exit_code


__all__ = [
    "Case",
    "CaseReport",
    "Expectation",
    "Got",
    "ImageReport",
    "Report",
    "Tolerances",
    "case_from_recording",
    "compare",
    "expected_yaml",
    "find_cases",
    "golden_command",
    "load_case",
    "pose_error",
    "result_entry",
    "run_case",
    "run_cases",
]
