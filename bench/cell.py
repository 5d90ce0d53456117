"""The benchmarks' vision cell: the example cell's inspections served over request cameras, and
sample images rendered by the simulated cell.

``write_config(workdir)`` turns ``examples/cell.yaml`` into a configuration whose cameras all
take their images in the request (a benchmark sends the images itself): the example's
inspections unchanged, plus ``station_pose_corners`` (the corner method, rescaled to the code's
printed side like the plane method) and ``station_pose_paper`` (the paper's corner method
exactly: depth only), plus for section 3 a copy of each inspection at 1024x768 and at 640x480
(``NAME-WxH``, on cameras ``CAMERA-WxH`` whose intrinsics are scaled; a circle locate's radius
range in pixels is scaled with them). ``load_catalog`` builds the catalog the way the server's
command line does (:class:`vision_server.service.runtime.CellRuntime`) and adds the built-in
``brightness`` inspection.
"""

from __future__ import annotations

import copy
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import yaml
from numpy.typing import NDArray

from geometry import transform_from_xyz_rpy

from .common import ROOT, SCENE, Skip

EXAMPLE_CONFIG = ROOT / "examples" / "cell.yaml"
SIZES: tuple[tuple[int, int], ...] = ((1024, 768), (640, 480))
"""(width, height) of section 3."""
SIZE_NAMES = {f"{w}x{h}" for w, h in SIZES}
DOWN = (np.pi, 0.0, 0.0)
CONVEYOR_VIEW = transform_from_xyz_rpy([0.3, -0.55, 0.275], DOWN)
"""The tool camera above the conveyor, caps in view (simulation/benchmark.py's pose)."""
QR_VIEW = transform_from_xyz_rpy([0.25, -0.36, 0.35], [-np.pi / 2, 0.0, -np.pi / 2])
"""The RGB-D camera looking at the station's code from about 1 m (simulation/README.md)."""
QR_TEXT = "cellvision:station-1"
CORNERS_POSE = {
    "name": "station_pose_corners",
    "type": "qr_pose",
    "camera": "rgbd",
    "method": "corners",
    "expect": QR_TEXT,
    "side_m": 0.16,
}
PAPER_POSE = {
    "name": "station_pose_paper",
    "type": "qr_pose",
    "camera": "rgbd",
    "method": "corners",
    "expect": QR_TEXT,
}
"""The paper's method exactly: the corners' depths, without rescaling to the printed side."""
# Intrinsics of the scene's cameras, for the example's cameras that are not request cameras.
SCENE_CAMERA = {"qc": "qc_camera", "tool": "tool_camera", "rgbd": "rgbd"}

Image = NDArray[Any]


def _scene_intrinsics(camera: str) -> dict[str, Any]:
    from simulation.scene import load_scene

    spec = load_scene(SCENE).camera(camera)
    i = spec.intrinsics
    return {
        "width": i.width,
        "height": i.height,
        "fx": i.fx,
        "fy": i.fy,
        "cx": i.cx,
        "cy": i.cy,
        "distortion": [float(d) for d in i.dist],
    }


def _scaled(intr: dict[str, Any], width: int, height: int) -> dict[str, Any]:
    sx, sy = width / intr["width"], height / intr["height"]
    return {
        "width": width,
        "height": height,
        "fx": intr["fx"] * sx,
        "fy": intr["fy"] * sy,
        # pixel centres: (0, 0) is the centre of the top-left pixel in both images
        "cx": (intr["cx"] + 0.5) * sx - 0.5,
        "cy": (intr["cy"] + 0.5) * sy - 0.5,
        "distortion": list(intr.get("distortion", [0.0] * 5)),
    }


def config_dict() -> dict[str, Any]:
    example = yaml.safe_load(EXAMPLE_CONFIG.read_text())
    cameras: dict[str, Any] = {}
    for name, cam in example["cameras"].items():
        intr = cam.get("intrinsics") or _scene_intrinsics(SCENE_CAMERA.get(name, name))
        cameras[name] = {"source": "request", "intrinsics": intr}
        if cam.get("depth"):
            cameras[name]["depth"] = True
    inspections = list(example["inspections"])
    for extra in (CORNERS_POSE, PAPER_POSE):
        if not any(i.get("name") == extra["name"] for i in inspections):
            inspections.append(dict(extra))
    sized = []
    for width, height in SIZES:
        suffix = f"-{width}x{height}"
        for name, cam in list(cameras.items()):
            if "-" in name and name.rsplit("-", 1)[1] in SIZE_NAMES:
                continue
            scaled = dict(cam, intrinsics=_scaled(cam["intrinsics"], width, height))
            cameras[name + suffix] = scaled
        for insp in inspections:
            copy_ = copy.deepcopy(insp)
            native = cameras[insp["camera"]]["intrinsics"]
            factor = width / native["width"]
            copy_["name"] = insp["name"] + suffix
            copy_["camera"] = insp["camera"] + suffix
            if "roi" in insp and factor != 1.0:
                copy_["roi"] = [int(round(v * factor)) for v in insp["roi"]]
            circle = copy_.get("circle")
            if isinstance(circle, dict) and factor != 1.0:
                for key in ("min_radius_px", "max_radius_px"):
                    if key in circle:
                        circle[key] = float(circle[key]) * factor
            sized.append(copy_)
    return {
        "server": {"name": "cellvision-bench"},
        "cameras": cameras,
        "inspections": inspections + sized,
    }


def write_config(workdir: Path) -> Path:
    path = workdir / "bench-cell.yaml"
    path.write_text(yaml.safe_dump(config_dict(), sort_keys=False))
    return path


@dataclass(frozen=True)
class BenchCatalog:
    """The catalog to serve, and why it lacks the configured inspections if it does."""

    catalog: Any
    problem: str | None


@dataclass(frozen=True)
class CircleLocate:
    """Stand-in for the configured ``cap_locate`` while the configuration does not load: the
    same analysis (:func:`vision_server.analysis.locate.locate`, circle method, the example's
    radius range), without the configuration layer."""

    name: str = "cap_locate"
    camera: str = "tool"
    type: str = "locate"
    uses_depth: bool = False
    frames: int = 1

    def run(self, image: Any, *, overlay: bool) -> Any:
        from vision_server import InspectionOutcome
        from vision_server.analysis import locate

        found = locate(image.color, method="circle", radius_range=(60.0, 100.0), polarity="bright")
        features = [{"u": f.u, "v": f.v, "score": f.score, "radius": f.radius} for f in found]
        return InspectionOutcome(bool(found), {"count": len(found), "features": features})


ANY_SIZE_CAMERA = "any-size"
ANY_SIZE_BRIGHTNESS = "brightness-any-size"
"""``brightness`` on a request camera without intrinsics, for images of any size."""


def load_catalog(config: Path | None) -> BenchCatalog:
    """The configured inspections plus ``brightness``. When the configuration does not load
    (the inspections are still being written): ``brightness`` and, if the analysis exists, a
    stand-in ``cap_locate`` (:class:`CircleLocate`), with the reason."""
    from vision_server import Catalog, builtin_catalog
    from vision_server.cameras import RequestCamera, RequestCameraSettings
    from vision_server.service.builtin import MeanIntensityPresence

    builtin = builtin_catalog()
    if config is None:
        return BenchCatalog(builtin, "no configuration given")
    try:
        from vision_server.service import CellRuntime

        runtime = CellRuntime(config)
    except Exception as exc:  # noqa: BLE001 - any failure means: serve what works, say why
        problem = f"the bench configuration does not load: {type(exc).__name__}: {exc}"
        try:
            import vision_server.analysis.locate  # noqa: F401
        except ImportError:
            return BenchCatalog(builtin, problem)
        fallback = Catalog.build(
            list(builtin.cameras.values()), [*builtin.inspections.values(), CircleLocate()]
        )
        return BenchCatalog(fallback, problem + "; cap_locate is a stand-in (CircleLocate)")
    cameras = list(runtime.catalog.cameras.values())
    inspections = list(runtime.catalog.inspections.values())
    for name, inspection in builtin.inspections.items():
        if name not in runtime.catalog.inspections:
            inspections.append(inspection)
            camera = builtin.cameras[inspection.camera]
            if camera.name not in runtime.catalog.cameras:
                cameras.append(camera)
    # Section 1's large images go to a camera that declares no size: the tool camera's
    # intrinsics (1024x768) refuse a 4096x3000 image (SPEC §4: an image must be its camera's).
    cameras.append(RequestCamera(ANY_SIZE_CAMERA, RequestCameraSettings()))
    inspections.append(MeanIntensityPresence(ANY_SIZE_BRIGHTNESS, ANY_SIZE_CAMERA, 64.0, 255.0))
    return BenchCatalog(Catalog.build(cameras, inspections), None)


def require(catalog: BenchCatalog, *names: str) -> None:
    """Raise :class:`Skip` unless the catalog has every inspection in ``names``."""
    missing = [n for n in names if n not in catalog.catalog.inspections]
    if missing:
        why = catalog.problem or "not in the configuration"
        raise Skip(f"inspection(s) {', '.join(missing)} unavailable ({why})")


# --- images ------------------------------------------------------------------------------------


@dataclass(frozen=True)
class Samples:
    """Rendered frames: the tool camera over the conveyor (gray 1024x768), the QC camera
    (gray 1024x768), the RGB-D camera at the station (BGR 640x480 and ``depth`` frames)."""

    tool: Image
    qc: Image
    rgbd: Image
    depth: tuple[Image, ...]


def render_samples(depth_frames: int = 5, seed: int = 3) -> Samples:
    from simulation import SimCell

    cell = SimCell.from_yaml(SCENE, seed=seed)
    cell.robot.move_linear(CONVEYOR_VIEW)
    tool = cell.render("tool_camera").color
    qc = cell.render("qc_camera").color
    cell.robot.move_linear(QR_VIEW)
    frames = [cell.render("rgbd") for _ in range(depth_frames)]
    depth = tuple(f.depth for f in frames if f.depth is not None)
    return Samples(tool, qc, frames[0].color, depth)


def resized(image: Image, width: int, height: int, *, depth: bool = False) -> Image:
    if image.shape[1] == width and image.shape[0] == height:
        return image
    if depth:
        interp = cv2.INTER_NEAREST
    elif width < image.shape[1]:
        interp = cv2.INTER_AREA
    else:
        interp = cv2.INTER_LINEAR
    return np.ascontiguousarray(cv2.resize(image, (width, height), interpolation=interp))
