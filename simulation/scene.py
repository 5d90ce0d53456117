"""The static scene: what the cell is made of, loaded from YAML into frozen dataclasses.

World frame: z up, metres, radians. Poses in YAML are ``{xyz: [x, y, z], rpy: [r, p, y]}``
(rpy as in ``geometry.rotation_from_rpy``: extrinsic X-Y-Z) or, for fixed cameras,
``{eye: [...], target: [...], up: [0, 0, 1]}``. Colours are BGR in [0, 255] (albedo under full
light) or one gray level. See examples/scenes/grundfos_cell.yaml for every key.

The scene never changes while the cell runs; what moves (parts, the robot) is in ``World``.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from geometry import CameraIntrinsics, make_transform, transform_from_xyz_rpy
from simulation import _yaml as y
from simulation._yaml import SceneError, SceneNode
from simulation.calibration_board import CalibrationBoardSpec

__all__ = [
    "BinSpec",
    "BoxSpec",
    "CameraSpec",
    "DepthSpec",
    "GripperSpec",
    "LightSpec",
    "PartSpec",
    "QRBoardSpec",
    "RobotSpec",
    "Scene",
    "SceneError",
    "SurfaceSpec",
    "SwitchSpec",
    "TextureSpec",
    "camera_preset",
    "load_scene",
    "parse_scene",
    "scene_from_text",
]

FloatArray = NDArray[np.float64]
Color = tuple[float, float, float]

PART_TYPES = ("rotor_cap", "rotor_core", "magnet")


@dataclass(frozen=True)
class TextureSpec:
    """A low-contrast decorative texture: ``stripes`` across x of the surface, or ``noise``."""

    kind: str
    period_m: float
    contrast: float


@dataclass(frozen=True)
class SurfaceSpec:
    """A horizontal work surface (conveyor, table, floor): a rectangle at ``height`` metres.

    ``center`` (x, y) and ``yaw`` place it in the world; ``size`` is (length along its x,
    width along its y). Its frame ``world_from_surface`` has its origin at the centre of the top.
    """

    name: str
    kind: str
    center: tuple[float, float]
    height: float
    size: tuple[float, float]
    yaw: float
    color: Color
    texture: TextureSpec | None

    @property
    def world_from_surface(self) -> FloatArray:
        return transform_from_xyz_rpy([*self.center, self.height], [0.0, 0.0, self.yaw])


@dataclass(frozen=True)
class PartSpec:
    """A movable part. Its frame: origin at the centre of its bottom, z up.

    rotor_cap and rotor_core are cylinders (``radius``, ``height``); magnet is a box
    (``size`` = (x, y, z)). The grasp point is ``grasp_depth_m`` below the top centre.
    ``jitter_xy_m`` / ``jitter_yaw`` randomise the initial pose (drawn from the scene seed).
    ``world_from_delivered``: where another station of the line puts the part (the magnet in its
    slot beside the rotor core), exactly, when :meth:`SimCell.deliver` runs; None: nobody does.
    """

    name: str
    type: str
    world_from_part: FloatArray
    radius: float
    height: float
    size: tuple[float, float, float]
    color: Color
    grasp_depth_m: float
    jitter_xy_m: float
    jitter_yaw: float
    world_from_delivered: FloatArray | None = None

    @property
    def top_height(self) -> float:
        return self.size[2] if self.type == "magnet" else self.height


@dataclass(frozen=True)
class BinSpec:
    """An open box that parts can be dropped into. Frame origin at the centre of its bottom;
    its floor (inside) is ``wall_m`` thick."""

    name: str
    world_from_bin: FloatArray
    size: tuple[float, float, float]
    wall_m: float
    color: Color


@dataclass(frozen=True)
class BoxSpec:
    """A static box (a panel, a pillar, a fixture). Frame origin at the centre of its bottom."""

    name: str
    world_from_box: FloatArray
    size: tuple[float, float, float]
    color: Color


@dataclass(frozen=True)
class QRBoardSpec:
    """A QR code printed on a white board.

    ``world_from_board``: origin at the centre of the code, x to the right of the print, y up
    the print, z out of the print (towards a viewer). The QR frame of docs/conventions.md is
    ``world_from_qr = world_from_board @ BOARD_FROM_QR``. ``side_m`` is the side of the symbol
    (dark-module boundary, no quiet zone); ``margin_m`` is the white border around it.
    """

    name: str
    text: str
    side_m: float
    margin_m: float
    world_from_board: FloatArray
    dark: Color
    light: Color


@dataclass(frozen=True)
class SwitchSpec:
    """A switch (the paper's point of interest). Frame origin at the centre of its front face,
    z out of that face; the body extends ``size[2]`` behind it."""

    name: str
    world_from_switch: FloatArray
    size: tuple[float, float, float]
    color: Color


@dataclass(frozen=True)
class GripperSpec:
    """Grasp succeeds when the TCP lies within ``tolerance_xy_m`` (horizontally) and
    ``tolerance_z_m`` (vertically) of a part's grasp point."""

    tolerance_xy_m: float = 0.004
    tolerance_z_m: float = 0.008


@dataclass(frozen=True)
class RobotSpec:
    """The arm: ``world_from_base`` (its mount), ``home`` (base_from_tool), linear speed,
    workspace box in the base frame, the gripper, and the simulated-time scale
    (0: never wait; 1: real time; k: k times faster than real time). ``repeatability_m`` and
    ``repeatability_rad``: one standard deviation of where the tool truly ends up against
    where the arm says it is (per axis, metres; about a random axis, radians); 0: exact."""

    world_from_base: FloatArray
    home: FloatArray
    speed_m_s: float
    angular_speed_rad_s: float
    workspace_min: tuple[float, float, float]
    workspace_max: tuple[float, float, float]
    time_scale: float
    gripper: GripperSpec
    docking_error_xy_m: float
    docking_error_yaw: float
    repeatability_m: float = 0.0
    repeatability_rad: float = 0.0


@dataclass(frozen=True)
class DepthSpec:
    """Structured-light depth (Kinect / Xtion) after Khoshelham & Elberink (2012).

    Disparity d = fb / z (px) gets Gaussian noise ``disparity_sigma_px`` and is quantised to
    1/``subpixel_steps`` px; z = fb / d. Pixels outside ``range_m``, at depth discontinuities
    (neighbour jump > ``edge_jump_m`` + ``edge_jump_rel`` * z) and a random ``dropout`` fraction
    read 0. ``misregistration_px`` shifts depth against colour; ``scale_bias`` scales z.
    """

    fb_px_m: float = 43.5
    disparity_sigma_px: float = 0.06
    subpixel_steps: int = 8
    range_m: tuple[float, float] = (0.5, 3.5)
    dropout: float = 0.002
    edge_jump_m: float = 0.01
    edge_jump_rel: float = 0.01
    misregistration_px: tuple[float, float] = (0.0, 0.0)
    scale_bias: float = 0.0


@dataclass(frozen=True)
class CameraSpec:
    """A camera: ``mount`` 'tool' (pose = tool_from_camera) or 'fixed' (pose = world_from_camera).

    ``noise_sigma`` is the Gaussian sensor noise in grey levels, ``blur_sigma_px`` an optional
    optical blur, ``vignetting`` the relative brightness loss at the image corners.
    """

    name: str
    mount: str
    pose: FloatArray
    intrinsics: CameraIntrinsics
    channels: int
    noise_sigma: float
    blur_sigma_px: float
    vignetting: float
    depth: DepthSpec | None


@dataclass(frozen=True)
class LightSpec:
    """A directional light (``direction`` points from the light into the scene) plus ambient."""

    direction: tuple[float, float, float] = (0.3, 0.2, -1.0)
    ambient: float = 0.45
    diffuse: float = 0.55


@dataclass(frozen=True)
class Scene:
    name: str
    seed: int
    source: str
    light: LightSpec
    background: Color
    surfaces: tuple[SurfaceSpec, ...]
    parts: tuple[PartSpec, ...]
    bins: tuple[BinSpec, ...]
    boxes: tuple[BoxSpec, ...]
    qr_boards: tuple[QRBoardSpec, ...]
    switches: tuple[SwitchSpec, ...]
    robot: RobotSpec
    cameras: tuple[CameraSpec, ...]
    calibration_boards: tuple[CalibrationBoardSpec, ...] = ()

    def camera(self, name: str) -> CameraSpec:
        for cam in self.cameras:
            if cam.name == name:
                return cam
        raise KeyError(f"no camera named {name!r} (have: {[c.name for c in self.cameras]})")

    def part(self, name: str) -> PartSpec:
        for part in self.parts:
            if part.name == name:
                return part
        raise KeyError(f"no part named {name!r}")

    def with_seed(self, seed: int) -> Scene:
        return replace(self, seed=seed)


def camera_preset(model: str) -> tuple[CameraIntrinsics, int, DepthSpec | None]:
    """Intrinsics, channel count and depth model of a named camera model.

    ``dmk31bf03``: a 1024x768 monochrome industrial camera (the paper's DMK 31BF03) with a
    lens of about 6.5 mm (fx = fy = 1400 px) and mild barrel distortion.
    ``xtion``: a 640x480 RGB-D camera like the Asus Xtion Pro Live, colour and depth
    registered and undistorted (fx = fy = 570.3 px).
    """
    if model == "dmk31bf03":
        intr = CameraIntrinsics(
            1024, 768, 1400.0, 1400.0, 511.5, 383.5, (-0.08, 0.05, 0.0004, -0.0003, 0.0)
        )
        return intr, 1, None
    if model == "xtion":
        return CameraIntrinsics(640, 480, 570.3, 570.3, 319.5, 239.5), 3, DepthSpec()
    raise ValueError(f"unknown camera model {model!r} (known: dmk31bf03, xtion)")


# --- parsing -------------------------------------------------------------------------------


def _pose(reader: SceneNode, *, allow_look_at: bool = False) -> FloatArray:
    if reader.has("eye"):
        if not allow_look_at:
            raise reader.error("look-at poses (eye/target) are only allowed for fixed cameras")
        eye = np.array(reader.take("eye", y.vec3))
        target = np.array(reader.take("target", y.vec3))
        up = np.array(reader.take("up", y.vec3, (0.0, 0.0, 1.0)))
        reader.finish()
        z = target - eye
        if np.linalg.norm(z) < 1e-9:
            raise reader.error("eye and target must differ")
        z /= np.linalg.norm(z)
        down = -(up - (up @ z) * z)
        if np.linalg.norm(down) < 1e-9:
            raise reader.error("up must not be parallel to the viewing direction")
        yv = down / np.linalg.norm(down)
        return make_transform(np.column_stack([np.cross(yv, z), yv, z]), eye)
    xyz = reader.take("xyz", y.vec3)
    rpy = reader.take("rpy", y.vec3, (0.0, 0.0, 0.0))
    reader.finish()
    return transform_from_xyz_rpy(xyz, rpy)


class _Supports:
    """Heights of named surfaces, bins and boxes, for ``support: name`` placements."""

    def __init__(self) -> None:
        self.tops: dict[str, float] = {}

    def place(self, reader: SceneNode, yaw_key: str = "yaw") -> FloatArray:
        """A pose from ``at`` + ``support`` (+ ``yaw``), or from ``pose``.

        (Not ``on``: YAML 1.1 reads the key ``on`` as the boolean true.)
        """
        if reader.has("pose"):
            return _pose(reader.sub("pose", required=True))
        at = reader.take("at", y.vec2)
        name = reader.take("support", y.string)
        if name not in self.tops:
            known = ", ".join(self.tops)
            raise reader.error(f"unknown support {name!r} (known: {known})", "support")
        yaw = reader.take(yaw_key, y.number, 0.0)
        return transform_from_xyz_rpy([at[0], at[1], self.tops[name]], [0.0, 0.0, yaw])


def _unique(name: str, seen: set[str], reader: SceneNode) -> str:
    if name in seen:
        raise reader.error(f"duplicate name {name!r}", "name")
    seen.add(name)
    return name


def _surface(r: SceneNode) -> SurfaceSpec:
    tex_reader = r.sub_optional("texture")
    texture = None
    if tex_reader is not None:
        texture = TextureSpec(
            kind=tex_reader.take("kind", y.one_of("stripes", "noise")),
            period_m=tex_reader.take("period_m", y.positive, 0.02),
            contrast=tex_reader.take("contrast", y.fraction, 0.05),
        )
        tex_reader.finish()
    size = r.take("size", y.vec2)
    if min(size) <= 0:
        raise r.error("sizes must be positive", "size")
    spec = SurfaceSpec(
        name=r.take("name", y.string),
        kind=r.take("kind", y.one_of("floor", "table", "conveyor", "station"), "table"),
        center=r.take("center", y.vec2),
        height=r.take("height", y.number),
        size=size,
        yaw=r.take("yaw", y.number, 0.0),
        color=r.take("color", y.color, (128.0, 128.0, 128.0)),
        texture=texture,
    )
    r.finish()
    return spec


_PART_DEFAULTS: dict[str, dict[str, Any]] = {
    "rotor_cap": {"radius": 0.02, "height": 0.025, "color": (200.0, 200.0, 200.0)},
    "rotor_core": {"radius": 0.035, "height": 0.06, "color": (125.0, 120.0, 120.0)},
    "magnet": {"size": (0.024, 0.012, 0.008), "color": (40.0, 40.0, 45.0)},
}


def _part(r: SceneNode, supports: _Supports) -> PartSpec:
    name = r.take("name", y.string)
    ptype = r.take("type", y.one_of(*PART_TYPES))
    defaults = _PART_DEFAULTS[ptype]
    world_from_part = supports.place(r)
    if ptype == "magnet":
        size = r.take("size", y.vec3, defaults["size"])
        if min(size) <= 0:
            raise r.error("sizes must be positive", "size")
        radius, height = 0.5 * float(np.hypot(size[0], size[1])), size[2]
    else:
        radius = r.take("radius", y.positive, defaults["radius"])
        height = r.take("height", y.positive, defaults["height"])
        size = (2 * radius, 2 * radius, height)
    jitter = r.sub_optional("jitter")
    jxy, jyaw = 0.0, 0.0
    if jitter is not None:
        jxy = jitter.take("xy_m", y.non_negative, 0.0)
        jyaw = jitter.take("yaw", y.non_negative, 0.0)
        jitter.finish()
    delivery = r.sub_optional("delivered")
    world_from_delivered = None
    if delivery is not None:
        world_from_delivered = supports.place(delivery)
        delivery.finish()
    spec = PartSpec(
        name=name,
        type=ptype,
        world_from_part=world_from_part,
        radius=radius,
        height=height,
        size=size,
        color=r.take("color", y.color, defaults["color"]),
        grasp_depth_m=r.take("grasp_depth_m", y.non_negative, 0.5 * height),
        jitter_xy_m=jxy,
        jitter_yaw=jyaw,
        world_from_delivered=world_from_delivered,
    )
    r.finish()
    return spec


def _box_size(r: SceneNode) -> tuple[float, float, float]:
    size = r.take("size", y.vec3)
    if min(size) <= 0:
        raise r.error("sizes must be positive", "size")
    return size


def _depth(r: SceneNode, base: DepthSpec) -> DepthSpec:
    rng = r.take("range_m", y.vec2, base.range_m)
    if not 0 < rng[0] < rng[1]:
        raise r.error("expected 0 < near < far", "range_m")
    steps = r.take("subpixel_steps", y.integer, base.subpixel_steps)
    if steps < 1:
        raise r.error("expected an integer >= 1", "subpixel_steps")
    spec = DepthSpec(
        fb_px_m=r.take("fb_px_m", y.positive, base.fb_px_m),
        disparity_sigma_px=r.take("disparity_sigma_px", y.non_negative, base.disparity_sigma_px),
        subpixel_steps=steps,
        range_m=rng,
        dropout=r.take("dropout", y.fraction, base.dropout),
        edge_jump_m=r.take("edge_jump_m", y.positive, base.edge_jump_m),
        edge_jump_rel=r.take("edge_jump_rel", y.non_negative, base.edge_jump_rel),
        misregistration_px=r.take("misregistration_px", y.vec2, base.misregistration_px),
        scale_bias=r.take("scale_bias", y.number, base.scale_bias),
    )
    r.finish()
    return spec


_INTRINSICS: tuple[tuple[str, Callable[[Any], float]], ...] = (
    ("width", y.integer),
    ("height", y.integer),
    ("fx", y.number),
    ("fy", y.number),
    ("cx", y.number),
    ("cy", y.number),
)


def _camera(r: SceneNode) -> CameraSpec:
    name = r.take("name", y.string)
    model = r.take("model", y.one_of("dmk31bf03", "xtion"), None)
    if model is not None:
        intr, channels, depth = camera_preset(model)
    else:
        intr, channels, depth = None, 3, None
    mount = r.take("mount", y.one_of("tool", "fixed"))
    pose = _pose(r.sub("pose", required=True), allow_look_at=mount == "fixed")
    ir = r.sub_optional("intrinsics")
    if ir is not None:
        base = intr
        fields: dict[str, Any] = {}
        # Without a model every intrinsic is required; with one, each defaults to the model's.
        for key, convert in _INTRINSICS:
            fields[key] = (
                ir.take(key, convert) if base is None else ir.take(key, convert, getattr(base, key))
            )
        fields["dist"] = ir.take("dist", y.vec5, base.dist if base else (0.0,) * 5)
        try:
            intr = CameraIntrinsics(**fields)
        except ValueError as exc:
            raise ir.error(str(exc)) from exc
        ir.finish()
    if intr is None:
        raise r.error("give a model or intrinsics", "intrinsics")
    channels = r.take("channels", y.integer, channels)
    if channels not in (1, 3):
        raise r.error("expected 1 or 3", "channels")
    if "depth" in r:  # a mapping of depth settings, or null for a colour-only camera
        dr = r.sub_optional("depth")
        depth = None if dr is None else _depth(dr, depth or DepthSpec())
    spec = CameraSpec(
        name=name,
        mount=mount,
        pose=pose,
        intrinsics=intr,
        channels=channels,
        noise_sigma=r.take("noise_sigma", y.non_negative, 1.5),
        blur_sigma_px=r.take("blur_sigma_px", y.non_negative, 0.0),
        vignetting=r.take("vignetting", y.fraction, 0.15),
        depth=depth,
    )
    r.finish()
    return spec


def _robot(r: SceneNode) -> RobotSpec:
    ws = r.sub("workspace", required=True)
    wmin = ws.take("min", y.vec3)
    wmax = ws.take("max", y.vec3)
    ws.finish()
    if not all(a < b for a, b in zip(wmin, wmax, strict=True)):
        raise ws.error("expected min < max on every axis")
    gr = r.sub_optional("gripper")
    gripper = GripperSpec()
    if gr is not None:
        gripper = GripperSpec(
            tolerance_xy_m=gr.take("tolerance_xy_m", y.positive, gripper.tolerance_xy_m),
            tolerance_z_m=gr.take("tolerance_z_m", y.positive, gripper.tolerance_z_m),
        )
        gr.finish()
    dock = r.sub_optional("docking_error")
    dxy, dyaw = 0.0, 0.0
    if dock is not None:
        dxy = dock.take("xy_m", y.non_negative, 0.0)
        dyaw = dock.take("yaw", y.non_negative, 0.0)
        dock.finish()
    rep = r.sub_optional("repeatability")
    rep_m, rep_rad = 0.0, 0.0
    if rep is not None:
        rep_m = rep.take("m", y.non_negative, 0.0)
        rep_rad = rep.take("rad", y.non_negative, 0.0)
        rep.finish()
    spec = RobotSpec(
        world_from_base=_pose(r.sub("world_from_base", required=True)),
        home=_pose(r.sub("home", required=True)),
        speed_m_s=r.take("speed_m_s", y.positive, 0.25),
        angular_speed_rad_s=r.take("angular_speed_rad_s", y.positive, 1.0),
        workspace_min=wmin,
        workspace_max=wmax,
        time_scale=r.take("time_scale", y.non_negative, 0.0),
        gripper=gripper,
        docking_error_xy_m=dxy,
        docking_error_yaw=dyaw,
        repeatability_m=rep_m,
        repeatability_rad=rep_rad,
    )
    r.finish()
    return spec


def parse_scene(reader: SceneNode) -> Scene:
    """Validate a parsed scene document (see :func:`load_scene`)."""
    names: set[str] = set()
    supports = _Supports()

    surfaces = []
    for sr in reader.items("surfaces"):
        s = _surface(sr)
        _unique(s.name, names, sr)
        supports.tops[s.name] = s.height
        surfaces.append(s)

    boxes = []
    for br in reader.items("boxes"):
        name = _unique(br.take("name", y.string), names, br)
        pose = supports.place(br)
        b = BoxSpec(name, pose, _box_size(br), br.take("color", y.color, (150.0, 150.0, 150.0)))
        br.finish()
        supports.tops[name] = float(pose[2, 3] + b.size[2])
        boxes.append(b)

    bins = []
    for br in reader.items("bins"):
        name = _unique(br.take("name", y.string), names, br)
        pose = supports.place(br)
        size = _box_size(br)
        wall = br.take("wall_m", y.positive, 0.005)
        if 2 * wall >= min(size[0], size[1]):
            raise br.error("walls too thick for the bin", "wall_m")
        bins.append(BinSpec(name, pose, size, wall, br.take("color", y.color, (60.0, 90.0, 160.0))))
        br.finish()
        supports.tops[name] = float(pose[2, 3] + wall)  # the floor is as thick as the walls

    parts = []
    for pr in reader.items("parts"):
        p = _part(pr, supports)
        _unique(p.name, names, pr)
        parts.append(p)

    boards = []
    for qr in reader.items("qr_boards"):
        name = _unique(qr.take("name", y.string), names, qr)
        side = qr.take("side_m", y.positive)
        boards.append(
            QRBoardSpec(
                name=name,
                text=qr.take("text", y.string),
                side_m=side,
                margin_m=qr.take("margin_m", y.non_negative, side * 0.2),
                world_from_board=_pose(qr.sub("pose", required=True)),
                dark=qr.take("dark", y.color, (20.0, 20.0, 20.0)),
                light=qr.take("light", y.color, (235.0, 235.0, 235.0)),
            )
        )
        qr.finish()

    calibration_boards = []
    for cb in reader.items("calibration_boards"):
        name = _unique(cb.take("name", y.string), names, cb)
        kind = cb.take("kind", y.one_of("charuco", "chessboard"))
        columns, rows = cb.take("columns", y.integer), cb.take("rows", y.integer)
        if columns < 3 or rows < 3:
            raise cb.error(f"a board needs at least 3 x 3 squares, got {columns} x {rows}")
        square = cb.take("square_m", y.positive)
        board_mount = cb.take("mount", y.one_of("fixed", "tool"), "fixed")
        calibration_boards.append(
            CalibrationBoardSpec(
                name=name,
                kind=kind,
                columns=columns,
                rows=rows,
                square_m=square,
                margin_m=cb.take("margin_m", y.non_negative, square / 2),
                world_from_board=_pose(cb.sub("pose", required=True)),
                mount=board_mount,
            )
        )
        cb.finish()

    switches = []
    for sw in reader.items("switches"):
        name = _unique(sw.take("name", y.string), names, sw)
        switches.append(
            SwitchSpec(
                name,
                _pose(sw.sub("pose", required=True)),
                sw.take("size", y.vec3, (0.03, 0.05, 0.02)),
                sw.take("color", y.color, (40.0, 40.0, 200.0)),
            )
        )
        sw.finish()

    cameras = []
    for cr in reader.items("cameras"):
        c = _camera(cr)
        _unique(c.name, names, cr)
        cameras.append(c)
    if not cameras:
        raise reader.error("a scene needs at least one camera", "cameras")

    light = LightSpec()
    lr = reader.sub_optional("light")
    if lr is not None:
        direction = lr.take("direction", y.vec3, light.direction)
        if np.linalg.norm(direction) < 1e-9:
            raise lr.error("must be non-zero", "direction")
        light = LightSpec(
            direction=direction,
            ambient=lr.take("ambient", y.fraction, light.ambient),
            diffuse=lr.take("diffuse", y.fraction, light.diffuse),
        )
        lr.finish()

    scene = Scene(
        name=reader.take("name", y.string),
        seed=reader.take("seed", y.integer, 0),
        source=reader.source,
        light=light,
        background=reader.take("background", y.color, (30.0, 30.0, 30.0)),
        surfaces=tuple(surfaces),
        parts=tuple(parts),
        bins=tuple(bins),
        boxes=tuple(boxes),
        qr_boards=tuple(boards),
        switches=tuple(switches),
        robot=_robot(reader.sub("robot", required=True)),
        cameras=tuple(cameras),
        calibration_boards=tuple(calibration_boards),
    )
    reader.finish()
    return scene


def load_scene(path: Path | str) -> Scene:
    """Load and validate a scene YAML file. Raises :class:`SceneError` naming file, line, key."""
    return parse_scene(y.load_yaml(path))


def scene_from_text(text: str, *, source: str = "<string>") -> Scene:
    """Parse a scene from YAML text (tests, examples)."""
    return parse_scene(y.parse_yaml(text, source=source))
