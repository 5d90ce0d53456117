"""Rendering the cell from one camera: colour, true depth and an object-label image.

Every solid is a set of convex planar faces (cylinders get as many side facets as their size in
the image calls for). Objects are drawn back to front in layers (surfaces, boxes, bins, boards
and switches, parts; by distance within a layer), with back faces culled. Small objects are
rasterised with exact supersampled coverage (see raster.py), so their edges, the QR modules and
the cap discs sit where the camera model puts them; large surfaces use OpenCV's anti-aliased
fill. Surface textures (low-contrast belt stripes, table grain) are mapped with the pinhole
homography and ignore lens distortion: they are decoration, not features.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

import cv2
import numpy as np
from numpy.typing import NDArray

from geometry import CameraIntrinsics, invert_transform, transform_points
from simulation.calibration_board import CalibrationBoardSpec, board_dark_quads
from simulation.qr import qr_modules
from simulation.raster import SHIFT, CameraRaster, inset_polygons, to_fixed
from simulation.scene import CameraSpec, LightSpec, PartSpec, Scene, SurfaceSpec
from simulation.sensor import NoiseBank, depth_image, vignette_map
from simulation.world import World

__all__ = ["RenderResult", "Renderer"]

FloatArray = NDArray[np.float64]
Color = tuple[float, float, float]

LAYER_SURFACE, LAYER_BOX, LAYER_BIN, LAYER_ATTACHED, LAYER_PART = range(5)
DEFAULT_BUDGET = 400_000  # supersamples per object
BOARD_BUDGET = 3_000_000
# A calibration board may fill the image, and its corners are what intrinsics are solved
# from: 8 x 8 samples per pixel up to a full 1024x768 frame (2x2 would quantise an edge
# parallel to the pixel grid to 0.5 px).
CALIBRATION_BOARD_BUDGET = 64 * 1024 * 768
TEXTURE_REDUCTION = 4
COLOR_STEP = 2.0  # grey levels; faces of a batch sharing a colour are filled together


@dataclass
class _Faces:
    """A batch of convex planar faces with the same vertex count."""

    points: FloatArray  # (n, K, 3) world
    normals: FloatArray  # (n, 3) outward, world
    colors: FloatArray  # (n, 3) shaded BGR
    dense: bool = False  # outlines already finely sampled (circles): never subdivide
    convex: bool = True  # front faces never overlap each other (faces of one convex solid)


@dataclass
class _Object:
    name: str
    layer: int
    centre: FloatArray
    radius: float  # bounding sphere
    build: Callable[[float], list[_Faces]]  # pixels per metre at the object -> faces
    decals: FloatArray | None = None  # (R, 4, 3) world quads drawn on the first face
    decal_color: Color = (0.0, 0.0, 0.0)
    background: bool = False
    budget: int = DEFAULT_BUDGET
    surface: SurfaceSpec | None = None


@dataclass
class RenderResult:
    """One rendered view. ``labels`` (H, W) holds the index into ``object_names`` of the
    object seen at each pixel centre (-1: nothing); ``depth_true_m`` is the noise-free z-depth
    (NaN: nothing), ``depth_mm`` the simulated sensor output (None for colour-only cameras)."""

    color: NDArray[np.uint8]
    labels: NDArray[np.int16]
    object_names: tuple[str, ...]
    depth_true_m: NDArray[np.float32] | None = None
    depth_mm: NDArray[np.uint16] | None = None


def _shade(colors: FloatArray, normals: FloatArray, light: LightSpec) -> FloatArray:
    """Lambertian shading of albedo ``colors`` (n, 3) for unit ``normals`` (n, 3)."""
    d = np.asarray(light.direction, dtype=np.float64)
    d = d / np.linalg.norm(d)
    k = light.ambient + light.diffuse * np.maximum(0.0, -(normals @ d))
    result: FloatArray = np.minimum(255.0, np.asarray(colors, dtype=np.float64) * k[:, None])
    return result


def _faces(
    points: FloatArray, normals: FloatArray, color: Color, light: LightSpec, dense: bool = False
) -> _Faces:
    normals = np.atleast_2d(normals)
    albedo = np.broadcast_to(np.asarray(color, dtype=np.float64), normals.shape)
    return _Faces(points, normals, _shade(albedo, normals, light), dense)


def _rect(pose: FloatArray, x0: float, x1: float, y0: float, y1: float, z: float) -> FloatArray:
    local = np.array([[x0, y0, z], [x1, y0, z], [x1, y1, z], [x0, y1, z]])
    return transform_points(pose, local)


_BOX_CORNERS = np.array([[-1, -1], [1, -1], [1, 1], [-1, 1]], dtype=np.float64)


def _box_faces(
    pose: FloatArray,
    size: tuple[float, float, float],
    color: Color,
    light: LightSpec,
    *,
    z0: float = 0.0,
) -> _Faces:
    """Faces of a box (x, y, z sizes) whose bottom centre is at (0, 0, z0) of ``pose``."""
    c = _BOX_CORNERS * np.array([size[0] / 2, size[1] / 2])
    bottom = np.column_stack([c, np.full(4, z0)])
    top = np.column_stack([c, np.full(4, z0 + size[2])])
    quads = [top, bottom[::-1]]
    normals = [(0.0, 0.0, 1.0), (0.0, 0.0, -1.0)]
    side_normals = [(0.0, -1.0, 0.0), (1.0, 0.0, 0.0), (0.0, 1.0, 0.0), (-1.0, 0.0, 0.0)]
    for i in range(4):
        j = (i + 1) % 4
        quads.append(np.array([bottom[i], bottom[j], top[j], top[i]]))
        normals.append(side_normals[i])
    pts = transform_points(pose, np.array(quads).reshape(-1, 3)).reshape(6, 4, 3)
    return _faces(pts, np.array(normals) @ pose[:3, :3].T, color, light)


def _cylinder_faces(
    pose: FloatArray, radius: float, height: float, color: Color, light: LightSpec, px_per_m: float
) -> list[_Faces]:
    r_px = px_per_m * radius
    n_top = int(np.clip(np.ceil(2 * np.pi * r_px / 3.0), 48, 720))
    n_side = int(np.clip(np.ceil(2 * np.pi * r_px / 8.0), 24, 96))
    a = np.linspace(0.0, 2 * np.pi, n_top, endpoint=False)
    top = np.column_stack([radius * np.cos(a), radius * np.sin(a), np.full(n_top, height)])
    up = pose[:3, 2].copy()
    faces = [_faces(transform_points(pose, top)[None], up, color, light, dense=True)]
    b = np.linspace(0.0, 2 * np.pi, n_side + 1)
    ring = np.column_stack([radius * np.cos(b), radius * np.sin(b)])
    lo = np.column_stack([ring, np.zeros(n_side + 1)])
    hi = np.column_stack([ring, np.full(n_side + 1, height)])
    quads = np.stack([lo[:-1], lo[1:], hi[1:], hi[:-1]], axis=1)  # (n, 4, 3)
    mid = 0.5 * (b[:-1] + b[1:])
    normals = np.column_stack([np.cos(mid), np.sin(mid), np.zeros(n_side)]) @ pose[:3, :3].T
    pts = transform_points(pose, quads.reshape(-1, 3)).reshape(n_side, 4, 3)
    faces.append(_faces(pts, normals, color, light))
    return faces


def _qr_quads(modules: NDArray[np.bool_], side: float) -> FloatArray:
    """Board-frame quads (R, 4, 3) of the horizontal runs of dark modules."""
    n = modules.shape[0]
    m = side / n
    quads = []
    for i in range(n):
        row = np.concatenate([[False], modules[i], [False]])
        edges = np.flatnonzero(np.diff(row.astype(np.int8)))
        for start, stop in zip(edges[::2], edges[1::2], strict=True):
            x0, x1 = -side / 2 + start * m, -side / 2 + stop * m
            y1, y0 = side / 2 - i * m, side / 2 - (i + 1) * m
            quads.append([[x0, y0, 0.0], [x1, y0, 0.0], [x1, y1, 0.0], [x0, y1, 0.0]])
    return np.array(quads, dtype=np.float64)


def _surface_texture(
    spec: SurfaceSpec, rng: np.random.Generator
) -> tuple[NDArray[np.uint8], float]:
    """A multiplicative texture (128 = 1.0) and its texel size in metres."""
    assert spec.texture is not None
    tex = spec.texture
    texel = max(tex.period_m / 6.0, max(spec.size) / 1024.0)
    w = max(2, int(np.ceil(spec.size[0] / texel)))
    h = max(2, int(np.ceil(spec.size[1] / texel)))
    if tex.kind == "stripes":
        x = (np.arange(w) + 0.5) * texel
        row = 1.0 + tex.contrast * np.sin(2 * np.pi * x / tex.period_m)
        factor = np.tile(row, (h, 1))
    else:
        coarse = rng.standard_normal((max(2, h // 8), max(2, w // 8)))
        factor = 1.0 + tex.contrast * cv2.resize(coarse, (w, h), interpolation=cv2.INTER_CUBIC)
    return np.clip(np.rint(128.0 * factor), 0, 255).astype(np.uint8), texel


@dataclass
class _CameraCache:
    raster: CameraRaster
    vignette: NDArray[np.uint8] | None
    noise: NoiseBank
    depth_noise: NoiseBank | None
    textures: dict[str, tuple[NDArray[np.uint8], float]] = field(default_factory=dict)


class Renderer:
    """Renders a :class:`Scene` in a given :class:`World` state; caches per-camera data."""

    def __init__(self, scene: Scene, seed: int) -> None:
        self.scene = scene
        self.seed = seed
        self._static = self._static_objects()
        self._cams: dict[str, _CameraCache] = {}
        self._textures: dict[str, tuple[NDArray[np.uint8], float]] = {}
        for i, s in enumerate(scene.surfaces):
            if s.texture is not None:
                self._textures[s.name] = _surface_texture(s, np.random.default_rng([seed, 7, i]))

    # --- scene to objects ----------------------------------------------------------------
    def _static_objects(self) -> list[_Object]:
        scene, light = self.scene, self.scene.light
        objs: list[_Object] = []

        def fixed(faces: list[_Faces]) -> Callable[[float], list[_Faces]]:
            return lambda _scale: faces

        def sphere(faces: list[_Faces]) -> tuple[FloatArray, float]:
            pts = np.concatenate([f.points.reshape(-1, 3) for f in faces])
            centre = 0.5 * (pts.min(axis=0) + pts.max(axis=0))
            return centre, float(np.linalg.norm(pts - centre, axis=1).max())

        for s in scene.surfaces:
            pose = s.world_from_surface
            pts = _rect(pose, -s.size[0] / 2, s.size[0] / 2, -s.size[1] / 2, s.size[1] / 2, 0.0)
            faces = [_faces(pts[None], pose[:3, 2], s.color, light)]
            c, r = sphere(faces)
            objs.append(
                _Object(s.name, LAYER_SURFACE, c, r, fixed(faces), background=True, surface=s)
            )
        for b in scene.boxes:
            faces = [_box_faces(b.world_from_box, b.size, b.color, light)]
            c, r = sphere(faces)
            objs.append(
                _Object(b.name, LAYER_BOX, c, r, fixed(faces), background=max(b.size) > 0.3)
            )
        for bn in scene.bins:
            sx, sy, sz = bn.size
            w = bn.wall_m
            pose = bn.world_from_bin
            floor = _rect(pose, -sx / 2 + w, sx / 2 - w, -sy / 2 + w, sy / 2 - w, w)
            groups = [_faces(floor[None], pose[:3, 2], bn.color, light)]
            walls = [
                ((0.0, -(sy - w) / 2), (sx, w)),
                ((0.0, (sy - w) / 2), (sx, w)),
                ((-(sx - w) / 2, 0.0), (w, sy - 2 * w)),
                (((sx - w) / 2, 0.0), (w, sy - 2 * w)),
            ]
            for (cx, cy), (wx, wy) in walls:
                wall_pose = pose.copy()
                wall_pose[:3, 3] = pose[:3, 3] + pose[:3, :3] @ np.array([cx, cy, 0.0])
                groups.append(_box_faces(wall_pose, (wx, wy, sz), bn.color, light))
            faces = [
                _Faces(
                    np.concatenate([g.points for g in groups]),
                    np.concatenate([g.normals for g in groups]),
                    np.concatenate([g.colors for g in groups]),
                    convex=False,
                )
            ]
            c, r = sphere(faces)
            objs.append(_Object(bn.name, LAYER_BIN, c, r, fixed(faces)))
        for q in scene.qr_boards:
            pose = q.world_from_board
            half = q.side_m / 2 + q.margin_m
            faces = [
                _faces(
                    _rect(pose, -half, half, -half, half, 0.0)[None], pose[:3, 2], q.light, light
                )
            ]
            quads = transform_points(pose, _qr_quads(qr_modules(q.text), q.side_m).reshape(-1, 3))
            dark = _shade(np.array([q.dark]), pose[:3, 2][None], light)[0]
            c, r = sphere(faces)
            objs.append(
                _Object(
                    q.name,
                    LAYER_ATTACHED,
                    c,
                    r,
                    fixed(faces),
                    decals=quads.reshape(-1, 4, 3),
                    decal_color=(float(dark[0]), float(dark[1]), float(dark[2])),
                    budget=BOARD_BUDGET,
                )
            )
        for cb in scene.calibration_boards:
            if cb.mount == "fixed":
                objs.append(self._calibration_board_object(cb, cb.world_from_board))
        for sw in scene.switches:
            faces = [_box_faces(sw.world_from_switch, sw.size, sw.color, light, z0=-sw.size[2])]
            c, r = sphere(faces)
            objs.append(_Object(sw.name, LAYER_ATTACHED, c, r, fixed(faces)))
        return objs

    def _calibration_board_object(self, cb: CalibrationBoardSpec, pose: FloatArray) -> _Object:
        """The board ``cb`` at ``pose`` (``world_from_board``, spec frame)."""
        light = self.scene.light
        half_w = cb.size_m[0] / 2 + cb.margin_m
        half_h = cb.size_m[1] / 2 + cb.margin_m
        faces = [
            _faces(
                _rect(pose, -half_w, half_w, -half_h, half_h, 0.0)[None],
                pose[:3, 2],
                cb.light,
                light,
            )
        ]
        quads = transform_points(pose, board_dark_quads(cb).reshape(-1, 3))
        dark = _shade(np.array([cb.dark]), pose[:3, 2][None], light)[0]
        pts = faces[0].points.reshape(-1, 3)
        centre = 0.5 * (pts.min(axis=0) + pts.max(axis=0))
        return _Object(
            cb.name,
            LAYER_ATTACHED,
            centre,
            float(np.linalg.norm(pts - centre, axis=1).max()),
            lambda _scale: faces,
            decals=quads.reshape(-1, 4, 3),
            decal_color=(float(dark[0]), float(dark[1]), float(dark[2])),
            budget=CALIBRATION_BOARD_BUDGET,
        )

    def _part_object(self, spec: PartSpec, pose: FloatArray) -> _Object:
        light = self.scene.light
        centre = pose[:3, 3] + pose[:3, 2] * spec.top_height / 2
        radius = float(np.hypot(spec.radius, spec.top_height / 2))
        if spec.type == "magnet":
            faces = [_box_faces(pose, spec.size, spec.color, light)]
            return _Object(spec.name, LAYER_PART, centre, radius, lambda _scale: faces)

        def build(px_per_m: float) -> list[_Faces]:
            return _cylinder_faces(pose, spec.radius, spec.height, spec.color, light, px_per_m)

        return _Object(spec.name, LAYER_PART, centre, radius, build)

    def raster(self, camera: CameraSpec) -> CameraRaster:
        """Projection helpers of ``camera`` (cached)."""
        return self._cache(camera).raster

    # --- camera cache ---------------------------------------------------------------------
    def _cache(self, camera: CameraSpec) -> _CameraCache:
        cache = self._cams.get(camera.name)
        if cache is None:
            intr = camera.intrinsics
            index = [c.name for c in self.scene.cameras].index(camera.name)
            shape: tuple[int, ...] = (intr.height, intr.width)
            if camera.channels == 3:
                shape = (*shape, 3)
            vig = None
            if camera.vignetting > 0:
                vig = vignette_map(intr.width, intr.height, intr.cx, intr.cy, camera.vignetting)
                if camera.channels == 3:
                    vig = _u8(cv2.merge([vig, vig, vig]))
            depth_bank = None
            if camera.depth is not None:
                depth_bank = NoiseBank(
                    np.random.default_rng([self.seed, 2, index]), (intr.height, intr.width)
                )
            cache = _CameraCache(
                raster=CameraRaster(intr),
                vignette=vig,
                noise=NoiseBank(np.random.default_rng([self.seed, 1, index]), shape),
                depth_noise=depth_bank,
            )
            self._cams[camera.name] = cache
        return cache

    # --- drawing ----------------------------------------------------------------------------
    def render(
        self,
        camera: CameraSpec,
        world_from_camera: FloatArray,
        world: World,
        rng: np.random.Generator,
    ) -> RenderResult:
        """Render ``camera`` at ``world_from_camera``; ``rng`` draws this frame's noise."""
        cache = self._cache(camera)
        intr = camera.intrinsics
        h, w, ch = intr.height, intr.width, camera.channels
        camera_from_world = invert_transform(world_from_camera)
        cam_pos = world_from_camera[:3, 3]
        frustum = cache.raster.frustum

        objects = list(self._static)
        for spec in self.scene.parts:
            objects.append(self._part_object(spec, world.part_pose(spec.name)))
        for cb in self.scene.calibration_boards:
            if cb.mount == "tool":  # moves with the flange: built for this frame's tool pose
                objects.append(
                    self._calibration_board_object(cb, cb.world_pose(world.world_from_tool()))
                )
        in_view = []
        for obj in objects:
            c_cam = camera_from_world[:3, :3] @ obj.centre + camera_from_world[:3, 3]
            if np.all(
                frustum[:, :3] @ c_cam + frustum[:, 3] >= -obj.radius * _plane_norms(frustum)
            ):
                in_view.append((obj, float(np.linalg.norm(obj.centre - cam_pos))))
        # Horizontal surfaces seen from above: the lower one is the farther one. Within the other
        # layers the farther object (by centre distance) is drawn first.
        in_view.sort(
            key=lambda item: (
                item[0].layer,
                item[0].centre[2] if item[0].layer == LAYER_SURFACE else -item[1],
            )
        )
        in_view = _drop_hidden_surfaces(in_view, camera_from_world, cache.raster)

        bg = self.scene.background
        img = np.empty((h, w, ch), np.uint8)
        img[:] = np.rint(np.array(bg if ch == 3 else [_gray(bg)], dtype=np.float64))
        names: list[str] = []
        planes: list[FloatArray] = []  # per face: (a, b, c) with 1/z = a x + b y + c
        face_owner: list[int] = []
        need_faces = camera.depth is not None
        face_labels = np.full((h, w), -1, np.int32 if need_faces else np.int16)
        f_mean = 0.5 * (intr.fx + intr.fy)

        for obj, dist in in_view:
            faces = obj.build(f_mean / max(dist, 0.05))
            roi = self._draw_object(
                obj,
                faces,
                img,
                face_labels,
                planes,
                face_owner,
                len(names),
                camera_from_world,
                cam_pos,
                cache,
                ch,
                need_faces,
            )
            if roi is not None:
                names.append(obj.name)
                if obj.surface is not None and obj.surface.name in self._textures:
                    self._apply_texture(img, roi, obj.surface, camera_from_world, intr, ch)

        if need_faces:
            labels = np.array([*face_owner, -1], dtype=np.int16)[face_labels]
        else:
            labels = face_labels  # object indices were drawn directly

        depth_true = None
        depth_mm = None
        if camera.depth is not None:
            depth_true = _true_depth(face_labels, planes, cache.raster)
            assert cache.depth_noise is not None
            depth_mm = depth_image(depth_true, camera.depth, rng, cache.depth_noise)

        if cache.vignette is not None:
            img = _u8(cv2.multiply(img, cache.vignette.reshape(img.shape), scale=1.0 / 255.0))
        if camera.blur_sigma_px > 0:
            img = _u8(cv2.GaussianBlur(img, (0, 0), camera.blur_sigma_px)).reshape(h, w, ch)
        if camera.noise_sigma > 0:
            noise = cache.noise.take_u8(rng, camera.noise_sigma).reshape(img.shape)
            img = _u8(cv2.addWeighted(img, 1.0, noise, 1.0, -128.0)).reshape(h, w, ch)
        color = img[:, :, 0].copy() if ch == 1 else img
        return RenderResult(color, labels, tuple(names), depth_true, depth_mm)

    def _draw_object(
        self,
        obj: _Object,
        faces: list[_Faces],
        img: NDArray[np.uint8],
        face_labels: NDArray[np.int32] | NDArray[np.int16],
        planes: list[FloatArray],
        face_owner: list[int],
        obj_index: int,
        camera_from_world: FloatArray,
        cam_pos: FloatArray,
        cache: _CameraCache,
        ch: int,
        need_faces: bool,
    ) -> tuple[int, int, int, int] | None:
        """Draw one object; returns its pixel ROI (x0, y0, x1, y1) or None if not seen."""
        h, w = img.shape[:2]
        rot, trans = camera_from_world[:3, :3], camera_from_world[:3, 3]
        groups: list[tuple[list[FloatArray], FloatArray, FloatArray, FloatArray, bool]] = []
        board_seen = False
        for gi, group in enumerate(faces):
            front = np.einsum("nj,nj->n", group.normals, group.points[:, 0] - cam_pos) < 0
            if not np.any(front):
                continue
            pts = group.points[front]
            pc = pts @ rot.T + trans
            normals_c = group.normals[front] @ rot.T
            dist = np.linalg.norm(pts.mean(axis=1) - cam_pos, axis=1)
            colors = group.colors[front]
            if cache.raster.inside_frustum(pc.reshape(-1, 3)):
                uv_list = list(cache.raster.project_batch(pc, dense=group.dense))
                keep = np.ones(len(pc), bool)
            else:
                uv_list, keep_l = [], []
                for poly in pc:
                    uv = cache.raster.project_polygon(poly, dense=group.dense)
                    keep_l.append(uv is not None)
                    if uv is not None:
                        uv_list.append(uv)
                keep = np.array(keep_l)
            if not uv_list:
                continue
            k = np.einsum("nj,nj->n", normals_c, pc[:, 0])
            groups.append(
                (uv_list, dist[keep], colors[keep], (normals_c / k[:, None])[keep], group.convex)
            )
            board_seen |= gi == 0
        if not groups:
            return None
        all_uv = np.concatenate([uv for g in groups for uv in g[0]])
        x0 = max(int(np.floor(all_uv[:, 0].min())) - 1, 0)
        y0 = max(int(np.floor(all_uv[:, 1].min())) - 1, 0)
        x1 = min(int(np.ceil(all_uv[:, 0].max())) + 2, w)
        y1 = min(int(np.ceil(all_uv[:, 1].max())) + 2, h)
        if x1 <= x0 or y1 <= y0:
            return None
        origin = np.array([x0, y0], dtype=np.float64)
        area = (x1 - x0) * (y1 - y0)
        s = 1 if obj.background else int(np.clip(np.floor(np.sqrt(obj.budget / area)), 1, 8))

        # Batches drawn back to front: faces of a convex batch never overlap each other, so one
        # fillPoly call per colour draws them (fillPoly XORs overlapping polygons).
        batches: list[tuple[float, list[_Entry]]] = []
        for uv_list, dist, colors, plane, convex in groups:
            local = [uv - origin for uv in uv_list]
            fine = _fixed_polys(local, s, inset=s > 1)
            coarse = _fixed_polys(local, 1, inset=False)  # labels sample pixel centres
            quantised = np.maximum(np.rint(colors / COLOR_STEP) * COLOR_STEP, 1.0)
            items = [
                _Entry(float(dist[i]), quantised[i], fine[i], coarse[i], plane[i])
                for i in range(len(local))
            ]
            if convex:
                batches.append((float(np.mean(dist)), items))
            else:
                batches.extend((e.distance, [e]) for e in items)
        batches.sort(key=lambda b: -b[0])

        decals: list[NDArray[np.int32]] = []
        if obj.decals is not None and board_seen:
            quads_c = (obj.decals.reshape(-1, 3) @ rot.T + trans).reshape(-1, 4, 3)
            decals = _fixed_polys(_decal_outlines(cache.raster, quads_c, origin), s, inset=s > 1)
        decal_color = _color(np.maximum(np.asarray(obj.decal_color), 1.0), ch)

        roi = img[y0:y1, x0:x1]
        line = cv2.LINE_AA if s == 1 else cv2.LINE_8
        hh, ww = y1 - y0, x1 - x0
        target = roi if s == 1 else np.zeros((hh * s, ww * s, ch), np.uint8)
        for _, items in batches:
            for color, polys in _by_color(items, fine=True):
                cv2.fillPoly(target, polys, _color(color, ch), line, SHIFT)
        if decals:
            cv2.fillPoly(target, decals, decal_color, line, SHIFT)
        if s > 1:
            # Every colour is >= 1, so the drawn samples are exactly the non-zero ones.
            _, mask = cv2.threshold(target[:, :, 0], 0, 255, cv2.THRESH_BINARY)
            premul = cv2.resize(target, (ww, hh), interpolation=cv2.INTER_AREA).reshape(hh, ww, ch)
            cov = cv2.resize(mask, (ww, hh), interpolation=cv2.INTER_AREA)
            alpha = cov.astype(np.float32)[:, :, None] * np.float32(1.0 / 255.0)
            blended = roi.astype(np.float32) * (1.0 - alpha) + premul.astype(np.float32)
            roi[:] = np.clip(np.rint(blended), 0, 255).astype(np.uint8)

        label_roi = face_labels[y0:y1, x0:x1]
        for _, items in batches:
            if need_faces:
                for e in items:
                    face_id = len(planes)
                    planes.append(e.plane)
                    face_owner.append(obj_index)
                    cv2.fillPoly(label_roi, [e.coarse], face_id, cv2.LINE_8, SHIFT)
            else:
                cv2.fillPoly(label_roi, [e.coarse for e in items], obj_index, cv2.LINE_8, SHIFT)
        return x0, y0, x1, y1

    def _apply_texture(
        self,
        img: NDArray[np.uint8],
        roi: tuple[int, int, int, int],
        s: SurfaceSpec,
        camera_from_world: FloatArray,
        intr: CameraIntrinsics,
        ch: int,
    ) -> None:
        tex, texel = self._textures[s.name]
        camera_from_surface = camera_from_world @ s.world_from_surface
        corners = _rect(
            camera_from_surface, -s.size[0] / 2, s.size[0] / 2, -s.size[1] / 2, s.size[1] / 2, 0.0
        )
        if np.any(corners[:, 2] <= 0.05):
            return  # a surface reaching behind the camera keeps its plain colour
        x0, y0, x1, y1 = roi
        # surface (x, y) = texel * (i + 0.5) - size / 2 at texture pixel i.
        surface_from_tex = np.array(
            [
                [texel, 0.0, texel / 2 - s.size[0] / 2],
                [0.0, texel, texel / 2 - s.size[1] / 2],
                [0.0, 0.0, 1.0],
            ]
        )
        roi_from_image = np.array([[1.0, 0.0, -x0], [0.0, 1.0, -y0], [0.0, 0.0, 1.0]])
        plane = camera_from_surface[:3][:, [0, 1, 3]]
        # The texture is smooth decoration: warp it at a quarter of the resolution, then scale.
        small = np.diag([1.0 / TEXTURE_REDUCTION, 1.0 / TEXTURE_REDUCTION, 1.0])
        pixel_shift = np.array([[1.0, 0.0, 0.5], [0.0, 1.0, 0.5], [0.0, 0.0, 1.0]])
        homography = (
            np.linalg.inv(pixel_shift)
            @ small
            @ pixel_shift
            @ roi_from_image
            @ intr.matrix
            @ plane
            @ surface_from_tex
        )
        ww, hh = x1 - x0, y1 - y0
        sw = max(1, -(-ww // TEXTURE_REDUCTION))
        sh = max(1, -(-hh // TEXTURE_REDUCTION))
        factor = cv2.warpPerspective(
            tex,
            homography,
            (sw, sh),
            flags=cv2.INTER_LINEAR,
            borderMode=cv2.BORDER_CONSTANT,
            borderValue=128,
        )
        factor = cv2.resize(
            factor, (sw * TEXTURE_REDUCTION, sh * TEXTURE_REDUCTION), interpolation=cv2.INTER_LINEAR
        )[:hh, :ww]
        if ch == 3:
            factor = cv2.merge([factor, factor, factor])
        part = img[y0:y1, x0:x1]
        part[:] = cv2.multiply(part, factor.reshape(part.shape), scale=1.0 / 128.0).reshape(
            part.shape
        )


@dataclass
class _Entry:
    distance: float
    color: FloatArray
    fine: NDArray[np.int32]
    coarse: NDArray[np.int32]
    plane: FloatArray


def _decal_outlines(
    raster: CameraRaster, quads_camera: FloatArray, origin: FloatArray
) -> list[FloatArray]:
    """Pixel outlines (relative to ``origin``) of decal quads (n, 4, 3) in the camera frame:
    those wholly in view projected together, those crossing the view's edge clipped one by one
    (a large calibration board seen in part), those out of view dropped."""
    planes = raster.frustum
    inside = np.all(quads_camera @ planes[:, :3].T + planes[:, 3] >= 0, axis=(1, 2))
    outlines: list[FloatArray] = []
    if np.any(inside):
        outlines.extend(raster.project_batch(quads_camera[inside], dense=False) - origin)
    for quad in quads_camera[~inside]:
        uv = raster.project_polygon(quad)
        if uv is not None and len(uv) >= 3:
            outlines.append(uv - origin)
    return outlines


def _by_color(
    items: list[_Entry], *, fine: bool
) -> list[tuple[FloatArray, list[NDArray[np.int32]]]]:
    groups: dict[tuple[float, ...], tuple[FloatArray, list[NDArray[np.int32]]]] = {}
    for e in items:
        key = tuple(e.color.tolist())
        if key not in groups:
            groups[key] = (e.color, [])
        groups[key][1].append(e.fine if fine else e.coarse)
    return list(groups.values())


def _drop_hidden_surfaces(
    in_view: list[tuple[_Object, float]], camera_from_world: FloatArray, raster: CameraRaster
) -> list[tuple[_Object, float]]:
    """Drop the surfaces drawn before a surface that fills the whole image (e.g. the floor
    under the conveyor when the tool camera looks down at the belt)."""
    lo_x, lo_y, hi_x, hi_y = raster.view_box
    box = np.array([[lo_x, lo_y], [hi_x, lo_y], [hi_x, hi_y], [lo_x, hi_y]])
    start = 0
    for i, (obj, _) in enumerate(in_view):
        if obj.layer != LAYER_SURFACE:
            break
        pc = obj.build(1.0)[0].points[0] @ camera_from_world[:3, :3].T + camera_from_world[:3, 3]
        if np.any(pc[:, 2] <= 1e-6):
            continue
        xy = pc[:, :2] / pc[:, 2:]
        # The image is covered when every view-box corner lies inside the (convex) outline.
        edges = np.roll(xy, -1, axis=0) - xy
        rel = box[:, None, :] - xy[None, :, :]
        cross = edges[None, :, 0] * rel[:, :, 1] - edges[None, :, 1] * rel[:, :, 0]
        if np.all(cross > 0) or np.all(cross < 0):
            start = i
    return in_view[start:]


def _plane_norms(planes: FloatArray) -> FloatArray:
    result: FloatArray = np.linalg.norm(planes[:, :3], axis=1)
    return result


def _fixed_polys(polys: list[FloatArray], s: int, *, inset: bool) -> list[NDArray[np.int32]]:
    """fillPoly coordinates of ROI polygons at ``s`` x supersampling (inset by half a sample)."""
    out: list[NDArray[np.int32]] = []
    by_len: dict[int, list[int]] = {}
    for i, p in enumerate(polys):
        by_len.setdefault(len(p), []).append(i)
    result: list[NDArray[np.int32] | None] = [None] * len(polys)
    for idx in by_len.values():
        batch = np.stack([polys[i] for i in idx])
        if s != 1:
            batch = (batch + 0.5) * s - 0.5
        if inset:
            batch = inset_polygons(batch, 0.5)
        fixed = to_fixed(batch)
        for j, i in enumerate(idx):
            result[i] = fixed[j]
    out = [r for r in result if r is not None]
    return out


def _u8(image: object) -> NDArray[np.uint8]:
    """OpenCV's result as a typed uint8 array (no copy)."""
    return np.asarray(image, dtype=np.uint8)


def _gray(color: Color) -> float:
    return 0.114 * color[0] + 0.587 * color[1] + 0.299 * color[2]


def _color(color: Color | FloatArray, ch: int) -> tuple[float, ...] | float:
    if ch == 1:
        return _gray((float(color[0]), float(color[1]), float(color[2])))
    return (float(color[0]), float(color[1]), float(color[2]))


def _true_depth(
    face_labels: NDArray[np.int32] | NDArray[np.int16],
    planes: list[FloatArray],
    raster: CameraRaster,
) -> NDArray[np.float32]:
    xn, yn = raster.normalized_grid
    # 1/z = a x + b y + c per face; label -1 picks the last (NaN) row.
    coeffs = np.array([*planes, np.array([np.nan, np.nan, np.nan])], dtype=np.float32).T.copy()
    inv = np.take(coeffs[0], face_labels) * xn
    inv += np.take(coeffs[1], face_labels) * yn
    inv += np.take(coeffs[2], face_labels)
    with np.errstate(divide="ignore", invalid="ignore"):
        z = np.float32(1.0) / inv
    z[~(inv > 0)] = np.nan
    result: NDArray[np.float32] = z.astype(np.float32, copy=False)
    return result
