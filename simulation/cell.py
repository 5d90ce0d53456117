"""``SimCell``: the simulated cell as one object (scene, world, robot, gripper, cameras).

Typical use::

    cell = SimCell.from_yaml("examples/scenes/grundfos_cell.yaml", seed=3)
    cell.robot.move_linear(pose)                 # base_from_tool, metres
    frame = cell.render("tool_camera")           # Frame(color, depth, truth)
    frame.truth.features["cap_1.top_centre"].uv  # exact pixel of a feature (with distortion)

Across processes, give both cells the same ``state_path``: every change the robot or gripper
makes is written there (see ``simulation.world``), and every ``render`` first adopts a newer
state from the file.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from geometry import CameraIntrinsics, invert_transform, transform_from_xyz_rpy, transform_points
from simulation.qr import BOARD_FROM_QR
from simulation.render import Renderer, RenderResult
from simulation.robot import Gripper, SimClock, SimRobot, support_below
from simulation.scene import Scene, load_scene
from simulation.world import PartState, World, WorldStateFile

__all__ = ["FeatureTruth", "Frame", "GroundTruth", "PartTruth", "QRTruth", "SimCell"]

FloatArray = NDArray[np.float64]


@dataclass(frozen=True)
class FeatureTruth:
    """A point feature: ``p_world``/``p_camera`` in metres, ``uv`` its distorted pixel
    position (NaN if behind the camera). ``visible``: inside the image and not hidden by another
    object (tested at the nearest pixel centre)."""

    name: str
    owner: str
    p_world: FloatArray
    p_camera: FloatArray
    uv: FloatArray
    in_image: bool
    visible: bool


@dataclass(frozen=True)
class QRTruth:
    """A QR code: corners c0..c3 (docs/conventions.md order) in world, camera and pixels, and
    the pose of the QR frame."""

    name: str
    text: str
    corners_world: FloatArray  # (4, 3)
    corners_camera: FloatArray  # (4, 3)
    corners_uv: FloatArray  # (4, 2)
    world_from_qr: FloatArray
    camera_from_qr: FloatArray
    visible: bool


@dataclass(frozen=True)
class PartTruth:
    name: str
    type: str
    world_from_part: FloatArray
    camera_from_part: FloatArray
    held: bool
    location: str


@dataclass(frozen=True)
class GroundTruth:
    """Everything true about one frame. ``labels`` (H, W): index into ``object_names`` of the
    object at each pixel (-1: none); ``depth_true_m``: noise-free z-depth (NaN: none)."""

    camera: str
    frame_index: int
    time_s: float
    intrinsics: CameraIntrinsics
    world_from_camera: FloatArray
    world_from_base: FloatArray
    base_from_camera: FloatArray
    base_from_tool: FloatArray
    features: dict[str, FeatureTruth]
    qr_codes: dict[str, QRTruth]
    parts: dict[str, PartTruth]
    labels: NDArray[np.int16]
    object_names: tuple[str, ...]
    depth_true_m: NDArray[np.float32] | None

    def mask(self, name: str) -> NDArray[np.bool_]:
        """Pixels (H, W) where object ``name`` is the nearest thing seen."""
        if name not in self.object_names:
            return np.zeros(self.labels.shape, bool)
        result: NDArray[np.bool_] = self.labels == self.object_names.index(name)
        return result


@dataclass(frozen=True)
class Frame:
    """One capture: ``color`` uint8 (H, W) or (H, W, 3) BGR; ``depth`` uint16 mm (0 = none) or
    None; ``truth`` the ground truth."""

    camera: str
    color: NDArray[np.uint8]
    depth: NDArray[np.uint16] | None
    truth: GroundTruth


class SimCell:
    """The simulated cell. All randomness derives from ``seed`` (default: the scene's)."""

    def __init__(
        self,
        scene: Scene,
        *,
        seed: int | None = None,
        state_path: Path | str | None = None,
    ) -> None:
        self.scene = scene
        self.seed = scene.seed if seed is None else seed
        self.world = self._initial_world()
        self._state = WorldStateFile(state_path) if state_path is not None else None
        self.clock = SimClock(self.world, scene.robot.time_scale)
        self.robot = SimRobot(
            scene.robot,
            self.world,
            self.clock,
            self._changed,
            rng=np.random.default_rng([self.seed, 7]),
        )
        self.gripper = Gripper(scene, self.world, self.clock, self._changed)
        self._renderer = Renderer(scene, self.seed)
        self._frames: dict[str, int] = {}
        self._dock_count = 0
        if self._state is not None:
            self.sync()

    @classmethod
    def from_yaml(
        cls, path: Path | str, *, seed: int | None = None, state_path: Path | str | None = None
    ) -> SimCell:
        return cls(load_scene(path), seed=seed, state_path=state_path)

    def _initial_world(self) -> World:
        rng = np.random.default_rng([self.seed, 0])
        parts = {}
        for spec in self.scene.parts:
            pose = spec.world_from_part
            if spec.jitter_xy_m > 0 or spec.jitter_yaw > 0:
                r = spec.jitter_xy_m * np.sqrt(rng.uniform())
                a = rng.uniform(0, 2 * np.pi)
                dyaw = rng.uniform(-1, 1) * spec.jitter_yaw
                pose = (
                    transform_from_xyz_rpy([r * np.cos(a), r * np.sin(a), 0.0], [0.0, 0.0, 0.0])
                    @ pose
                )
                pose = pose @ transform_from_xyz_rpy([0, 0, 0], [0, 0, dyaw])
            parts[spec.name] = PartState(world_from_part=pose.copy())
        return World(
            parts=parts,
            world_from_base=self.scene.robot.world_from_base.copy(),
            base_from_tool=self.scene.robot.home.copy(),
        )

    # --- state sharing ------------------------------------------------------------------
    def _changed(self) -> None:
        if self._state is not None:
            self._state.write(self.world)

    def sync(self) -> bool:
        """Adopt a newer world state from the state file; True if it changed."""
        if self._state is None:
            return False
        newer = self._state.read_if_changed()
        if newer is None:
            return False
        self.world.parts = newer.parts
        self.world.world_from_base = newer.world_from_base
        self.world.base_from_tool = newer.base_from_tool
        self.world.base_from_user = newer.base_from_user
        self.world.time_s = newer.time_s
        self.world.version = newer.version
        return True

    def publish(self) -> None:
        """Write the current world to the state file (after editing ``world`` directly)."""
        self.world.version += 1
        self._changed()

    def restart(self) -> None:
        """Start again from the scene (parts where it puts them, with the seed's jitter; the
        robot at home on its nominal mount; time 0) and write that to the state file, even if
        another run left a world there: the file's readers follow this writer from now on."""
        fresh = self._initial_world()
        self.world.parts = fresh.parts
        self.world.world_from_base = fresh.world_from_base
        self.world.base_from_tool = fresh.base_from_tool
        self.world.base_from_user = fresh.base_from_user
        self.world.time_s = fresh.time_s
        self.publish()

    def deliver(self, *names: str) -> list[str]:
        """The line's other stations deliver parts: each named part (none named: every part the
        scene gives a ``delivered`` pose) is put there, unless the gripper holds it. Returns the
        parts moved; writes the state file. KeyError for a part without a delivery pose."""
        wanted = names or tuple(
            p.name for p in self.scene.parts if p.world_from_delivered is not None
        )
        moved: list[str] = []
        for name in wanted:
            pose = self.scene.part(name).world_from_delivered
            if pose is None:
                raise KeyError(f"part {name!r} has no delivered pose in the scene")
            state = self.world.parts[name]
            if state.held:
                continue
            where, _ = support_below(self.scene, pose[:3, 3])
            self.world.parts[name] = PartState(world_from_part=pose.copy(), location=where)
            moved.append(name)
        if moved:
            self.publish()
        return moved

    def dock(self) -> FloatArray:
        """Simulate the mobile robot arriving at the cell again (random docking error)."""
        self._dock_count += 1
        return self.robot.dock(np.random.default_rng([self.seed, 3, self._dock_count]))

    # --- cameras ------------------------------------------------------------------------
    def world_from_camera(self, camera: str) -> FloatArray:
        spec = self.scene.camera(camera)
        if spec.mount == "tool":
            result: FloatArray = self.world.world_from_tool() @ spec.pose
            return result
        return spec.pose.copy()

    def render(self, camera: str) -> Frame:
        """Capture one frame from ``camera`` (new noise each call; deterministic per seed)."""
        self.sync()
        spec = self.scene.camera(camera)
        index = self._frames.get(camera, 0)
        self._frames[camera] = index + 1
        cam_index = [c.name for c in self.scene.cameras].index(camera)
        rng = np.random.default_rng([self.seed, 4, cam_index, index])
        world_from_camera = self.world_from_camera(camera)
        result = self._renderer.render(spec, world_from_camera, self.world, rng)
        truth = self._truth(camera, index, world_from_camera, result)
        return Frame(camera, result.color, result.depth_mm, truth)

    # --- ground truth -------------------------------------------------------------------
    def _truth(
        self, camera: str, index: int, world_from_camera: FloatArray, result: RenderResult
    ) -> GroundTruth:
        spec = self.scene.camera(camera)
        intr = spec.intrinsics
        camera_from_world = invert_transform(world_from_camera)
        world_from_base = self.world.world_from_base.copy()

        raster = self._renderer.raster(spec)
        pending: list[tuple[str, str, FloatArray]] = []
        parts: dict[str, PartTruth] = {}
        for pspec in self.scene.parts:
            pose = self.world.part_pose(pspec.name)
            state = self.world.parts[pspec.name]
            parts[pspec.name] = PartTruth(
                pspec.name, pspec.type, pose, camera_from_world @ pose, state.held, state.location
            )
            top = pose[:3, 3] + pose[:3, 2] * pspec.top_height
            pending.append((f"{pspec.name}.top_centre", pspec.name, top))
        for sw in self.scene.switches:
            pending.append((sw.name, sw.name, sw.world_from_switch[:3, 3].copy()))

        qr_codes: dict[str, QRTruth] = {}
        for q in self.scene.qr_boards:
            half = q.side_m / 2
            # c0 top-left, c1 top-right, c2 bottom-right, c3 bottom-left (board x right, y up)
            local = np.array(
                [[-half, half, 0], [half, half, 0], [half, -half, 0], [-half, -half, 0]],
                dtype=np.float64,
            )
            cw = transform_points(q.world_from_board, local)
            for i in range(4):
                pending.append((f"{q.name}.c{i}", q.name, cw[i]))
            pending.append((f"{q.name}.centre", q.name, q.world_from_board[:3, 3].copy()))

        features: dict[str, FeatureTruth] = {}
        if pending:
            p_world = np.array([p[2] for p in pending])
            p_cam = transform_points(camera_from_world, p_world)
            in_view = raster.in_view(p_cam)
            uv = np.full((len(pending), 2), np.nan)
            uv[in_view] = intr.project(p_cam[in_view])
            with np.errstate(invalid="ignore"):
                inside = (
                    in_view
                    & (uv[:, 0] >= -0.5)
                    & (uv[:, 0] < intr.width - 0.5)
                    & (uv[:, 1] >= -0.5)
                    & (uv[:, 1] < intr.height - 0.5)
                )
            for i, (name, owner, pw) in enumerate(pending):
                vis = False
                if inside[i]:
                    label = int(result.labels[int(np.rint(uv[i, 1])), int(np.rint(uv[i, 0]))])
                    vis = label >= 0 and result.object_names[label] == owner
                features[name] = FeatureTruth(
                    name, owner, pw, p_cam[i], uv[i], bool(inside[i]), vis
                )

        for q in self.scene.qr_boards:
            corners = [features[f"{q.name}.c{i}"] for i in range(4)]
            world_from_qr = q.world_from_board @ BOARD_FROM_QR
            qr_codes[q.name] = QRTruth(
                q.name,
                q.text,
                np.array([c.p_world for c in corners]),
                np.array([c.p_camera for c in corners]),
                np.array([c.uv for c in corners]),
                world_from_qr,
                camera_from_world @ world_from_qr,
                all(c.visible for c in corners),
            )

        return GroundTruth(
            camera=camera,
            frame_index=index,
            time_s=self.world.time_s,
            intrinsics=intr,
            world_from_camera=world_from_camera,
            world_from_base=world_from_base,
            base_from_camera=invert_transform(world_from_base) @ world_from_camera,
            base_from_tool=self.world.base_from_tool.copy(),
            features=features,
            qr_codes=qr_codes,
            parts=parts,
            labels=result.labels,
            object_names=result.object_names,
            depth_true_m=result.depth_true_m,
        )
