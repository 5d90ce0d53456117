"""Hand-eye calibration in the simulated cell (issue 18, part 2): the tool camera of
examples/scenes/intrinsics_cell.yaml (its arm given 0.03 mm / 0.01 deg repeatability: images
from where it truly is, poses as it reports them) moves through the 15 poses
``robot-client calibrate-hand-eye`` plans around the ChArUco board; corners from the server's
board detector (vision_server.analysis.board, in process), ``tool_from_camera`` solved by
robot_client.commissioning and compared with the scene's mount, over 20 seeds. Then the
whole chain: intrinsics and hand-eye calibrated from the camera's approximate description
(fx 1350 px instead of 1400, the mount 4 mm and 0.6 deg off), stored, and vision pick in the
Grundfos cell through the server's ``cap_locate`` with what was stored. And eye-to-hand: the
board bolted to the flange (examples/scenes/eye_to_hand_cell.yaml, same arm noise) shown to the
fixed QC camera at the 15 poses the command plans, ``base_from_camera`` against the truth."""

from __future__ import annotations

import math
import tempfile
import time
from dataclasses import replace
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import numpy as np

from geometry import (
    CameraIntrinsics,
    invert_transform,
    make_transform,
    rotation_angle,
    rotation_from_rpy,
    transform_from_xyz_rpy,
    transform_points,
)
from robot_client.commissioning import HandEyeResult, solve_hand_eye, solve_intrinsics
from robot_client.commissioning.collect import collect_tool_views
from robot_client.commissioning.hand_eye_collect import collect_hand_eye_views
from robot_client.devices import Devices
from robot_client.devices.sim import SimCamera, sim_devices
from simulation import SimCell, load_scene
from vision_server.analysis import BoardSpec, NotFoundError, detect_board

from .cell import require
from .common import ROOT, Goal, RunConfig, Section, Table, fmt
from .env import Env
from .plots import pyplot, save
from .servers import HOST

NAME = "hand_eye"
TITLE = "Hand-eye calibration and the whole chain (simulated cell)"
SCENE = ROOT / "examples" / "scenes" / "intrinsics_cell.yaml"
EYE_TO_HAND_SCENE = ROOT / "examples" / "scenes" / "eye_to_hand_cell.yaml"
PICK_SCENE = ROOT / "examples" / "scenes" / "grundfos_cell.yaml"
GOAL_T_MM = 0.3
GOAL_R_DEG = 0.05
GOAL_PICK_MM = 0.5
APPROXIMATE = CameraIntrinsics(1024, 768, 1350.0, 1350.0, 512.0, 384.0)
NOMINAL_MOUNT = make_transform(rotation_from_rpy(0.01, 0.0, 0.0), [0.074, 0.0, -0.1])
BOARD = BoardSpec("charuco", 11, 8, 0.03, 0.0225)
DOWN = [math.pi, 0.0, 0.0]
L1: dict[str, Any] = {  # the conveyor search line of the example cell (base frame)
    "p_cam_start": transform_from_xyz_rpy([0.05, -0.55, 0.275], DOWN),
    "p_cam_end": transform_from_xyz_rpy([0.55, -0.55, 0.275], DOWN),
    "h_detect": 0.025,
    "h_grasp": 0.0125,
    "step_m": 0.1,
}


class BoardVision:
    """The ``calibration_board`` inspection's RESULT data, computed in process (the bench
    measures accuracy; the wire is measured elsewhere)."""

    def inspect(self, inspection: str, image: Any = None, **kwargs: Any) -> Any:
        try:
            found = detect_board(image, BOARD)
        except NotFoundError as exc:
            return SimpleNamespace(data={"found": False, "reason": str(exc)})
        height, width = image.shape[:2]
        return SimpleNamespace(
            data={
                "found": True,
                "board": BOARD.kind,
                "squares": [BOARD.columns, BOARD.rows],
                "square_m": BOARD.square_m,
                "image_size": [width, height],
                "corners": found.uv.tolist(),
                "object_points": found.object_points.tolist(),
            }
        )


def commissioning_cell(seed: int) -> SimCell:
    """The commissioning cell, its arm off by the repeatability of a real one."""
    scene = load_scene(SCENE)
    robot = replace(scene.robot, repeatability_m=0.03e-3, repeatability_rad=math.radians(0.01))
    return SimCell(replace(scene, robot=robot), seed=seed)


def eye_to_hand(seed: int) -> tuple[HandEyeResult, float, float]:
    """The QC camera calibrated eye-to-hand with its true intrinsics; the pose's errors."""
    scene = load_scene(EYE_TO_HAND_SCENE)
    robot = replace(scene.robot, repeatability_m=0.03e-3, repeatability_rad=math.radians(0.01))
    cell = SimCell(replace(scene, robot=robot), seed=seed)
    spec = cell.scene.camera("qc_camera")
    vision: Any = BoardVision()  # duck-typed: only inspect() is used
    collected = collect_hand_eye_views(
        sim_devices(cell, vision=vision),
        camera="qc_camera",
        inspection="board",
        intrinsics=spec.intrinsics,
    )
    result = solve_hand_eye(collected.views, spec.intrinsics, collected.setup)
    truth = invert_transform(cell.scene.robot.world_from_base) @ spec.pose
    t_mm, r_deg = errors(result.camera, truth)
    return result, t_mm, r_deg


def _devices(cell: SimCell, vision: Any, **camera: Any) -> Devices:
    devices = sim_devices(cell, vision=vision)
    devices.cameras["tool_camera"] = SimCamera(cell, "tool_camera", **camera)
    return devices


def calibrate(cell: SimCell, intrinsics: CameraIntrinsics, **camera: Any) -> HandEyeResult:
    devices = _devices(cell, BoardVision(), **camera)
    collected = collect_hand_eye_views(
        devices, camera="tool_camera", inspection="board", intrinsics=intrinsics
    )
    return solve_hand_eye(collected.views, intrinsics)


def errors(found: np.ndarray, truth: np.ndarray) -> tuple[float, float]:
    """Translation (mm) and rotation (deg) between two poses."""
    return (
        float(np.linalg.norm(found[:3, 3] - truth[:3, 3])) * 1000.0,
        math.degrees(rotation_angle(found[:3, :3].T @ truth[:3, :3])),
    )


def commission(seed: int) -> tuple[CameraIntrinsics, HandEyeResult, float, float]:
    """Intrinsics, then hand-eye, from the approximate description; the mount's errors."""
    cell = commissioning_cell(seed)
    camera = {"nominal_mount": NOMINAL_MOUNT, "nominal_intrinsics": APPROXIMATE}
    views = collect_tool_views(
        _devices(cell, BoardVision(), **camera), camera="tool_camera", inspection="board"
    )
    assert views.image_size is not None
    intrinsics = solve_intrinsics(views.views, views.image_size).intrinsics
    result = calibrate(cell, intrinsics, **camera)
    t_mm, r_deg = errors(result.camera, cell.scene.camera("tool_camera").pose)
    return intrinsics, result, t_mm, r_deg


def pick(
    client: Any, intrinsics: CameraIntrinsics, result: HandEyeResult, seed: int
) -> list[float]:
    """The three caps on the conveyor picked with the calibrated camera: grasp errors (mm;
    NaN: the pick failed)."""
    from robot_client.skills import SkillContext, default_registry, execute
    from robot_client.skills.camera_mounts import hand_eye_record
    from robot_client.teach_store import TeachStore

    scene = load_scene(PICK_SCENE)
    robot = replace(scene.robot, repeatability_m=0.03e-3, repeatability_rad=math.radians(0.01))
    cell = SimCell(replace(scene, robot=robot), seed=seed)
    devices = _devices(cell, client, nominal_mount=NOMINAL_MOUNT, nominal_intrinsics=APPROXIMATE)
    folder = tempfile.TemporaryDirectory(prefix="cellvision-bench-hand-eye-")
    store = TeachStore(Path(folder.name) / "taught.yaml")
    store.put(
        hand_eye_record(
            "tool_camera",
            "eye_in_hand",
            result.camera,
            intrinsics=intrinsics,
            verdict=result.verdict,
            reasons=result.reasons,
            figures={},
        )
    )
    ctx = SkillContext.create(devices, store=store)
    skill = default_registry().get("vision_pick")
    record = skill.teach("l1", L1, ctx)
    out = []
    try:
        for k in range(3):
            ctx.robot.move_linear(L1["p_cam_start"])
            outcome = execute(skill, record, ctx)
            held = cell.gripper.held
            if not outcome.ok or held is None:
                out.append(float("nan"))
                break
            tool_from_world = invert_transform(cell.world.world_from_tool())
            grasp = transform_points(tool_from_world, cell.gripper.grasp_point(held))
            out.append(float(np.linalg.norm(grasp)) * 1000.0)
            ctx.gripper.open()
            ctx.world.held_part = None
            pose = cell.world.parts[held].world_from_part.copy()
            pose[:2, 3] = (2.0 + 0.1 * k, 2.0)  # onto the floor, out of sight
            cell.world.parts[held].world_from_part = pose
            cell.publish()
    finally:
        folder.cleanup()
    return out


def run(cfg: RunConfig, env: Env) -> Section:
    from robot_client import SyncVisionClient

    section = Section(NAME, TITLE)
    seeds = range(cfg.n(20, 2))
    table = Table(
        [
            "seed",
            "poses",
            "translation error mm",
            "rotation error deg",
            "RMS px",
            "loop mm / deg",
            "σ mm / deg",
            "verdict",
            "solve ms",
        ]
    )
    t_errors, r_errors = [], []
    for seed in seeds:
        cell = commissioning_cell(seed)
        truth = cell.scene.camera("tool_camera")
        devices = _devices(cell, BoardVision())
        collected = collect_hand_eye_views(
            devices, camera="tool_camera", inspection="board", intrinsics=truth.intrinsics
        )
        t0 = time.perf_counter()
        result = solve_hand_eye(collected.views, truth.intrinsics)
        solve_ms = (time.perf_counter() - t0) * 1000.0
        t_mm, r_deg = errors(result.camera, truth.pose)
        t_errors.append(t_mm)
        r_errors.append(r_deg)
        table.add(
            seed,
            len(result.views),
            fmt(t_mm, 3),
            fmt(r_deg, 4),
            fmt(result.rms_px, 3),
            f"{result.loop_translation_m * 1000:.3f} / "
            f"{math.degrees(result.loop_rotation_rad):.4f}",
            f"{result.sigma_translation_m * 1000:.3f} / "
            f"{math.degrees(result.sigma_rotation_rad):.4f}",
            result.verdict,
            fmt(solve_ms, 0),
        )
    p95_t = float(np.percentile(t_errors, 95))
    p95_r = float(np.percentile(r_errors, 95))
    section.value("p95_translation_mm", p95_t)
    section.value("p95_rotation_deg", p95_r)
    n = len(t_errors)
    section.goals.append(
        Goal(
            f"tool_from_camera p95 <= {GOAL_T_MM} mm and <= {GOAL_R_DEG} deg from <= 15 poses "
            f"({n} seeds, arm repeatability 0.03 mm / 0.01 deg)",
            f"p95 {p95_t:.3f} mm, {p95_r:.4f} deg (max {max(t_errors):.3f} mm, "
            f"{max(r_errors):.4f} deg)",
            p95_t <= GOAL_T_MM and p95_r <= GOAL_R_DEG,
        )
    )
    section.tables.append(table)

    fixed = Table(
        [
            "seed",
            "poses",
            "translation error mm",
            "rotation error deg",
            "RMS px",
            "loop mm / deg",
            "verdict",
        ]
    )
    fixed.caption = "Eye-to-hand: base_from_camera of the fixed QC camera, the board on the flange."
    fixed_t, fixed_r = [], []
    for seed in seeds:
        result, t_mm, r_deg = eye_to_hand(seed)
        fixed_t.append(t_mm)
        fixed_r.append(r_deg)
        fixed.add(
            seed,
            len(result.views),
            fmt(t_mm, 3),
            fmt(r_deg, 4),
            fmt(result.rms_px, 3),
            f"{result.loop_translation_m * 1000:.3f} / "
            f"{math.degrees(result.loop_rotation_rad):.4f}",
            result.verdict,
        )
    fixed_p95_t = float(np.percentile(fixed_t, 95))
    fixed_p95_r = float(np.percentile(fixed_r, 95))
    section.value("eye_to_hand_p95_translation_mm", fixed_p95_t)
    section.value("eye_to_hand_p95_rotation_deg", fixed_p95_r)
    section.goals.append(
        Goal(
            f"base_from_camera (eye-to-hand) p95 <= {GOAL_T_MM} mm and <= {GOAL_R_DEG} deg "
            f"from <= 15 poses ({len(fixed_t)} seeds, same arm noise)",
            f"p95 {fixed_p95_t:.3f} mm, {fixed_p95_r:.4f} deg (max {max(fixed_t):.3f} mm, "
            f"{max(fixed_r):.4f} deg)",
            fixed_p95_t <= GOAL_T_MM and fixed_p95_r <= GOAL_R_DEG,
        )
    )
    section.tables.append(fixed)

    # The whole chain: commissioned from the approximate description, then vision pick.
    server = env.server("cellvision")
    if "cap_locate" not in server.info["inspections"]:
        require(env.catalog, "cap_locate")
    chain = Table(["seed", "fx px", "mount error mm / deg", "verdict", "pick errors mm"])
    picks: list[float] = []
    client = SyncVisionClient(HOST, server.port, request_timeout_s=30.0)
    try:
        for seed in range(100, 100 + cfg.n(5, 1)):
            intrinsics, result, t_mm, r_deg = commission(seed)
            errors_mm = pick(client, intrinsics, result, seed)
            picks += errors_mm
            chain.add(
                seed,
                fmt(intrinsics.fx, 2),
                f"{t_mm:.3f} / {r_deg:.4f}",
                result.verdict,
                ", ".join(fmt(e, 3) for e in errors_mm),
            )
    finally:
        client.close()
    grasped = [e for e in picks if e == e]
    failed = len(picks) - len(grasped)
    p95_pick = float(np.percentile(grasped, 95)) if grasped else float("nan")
    section.value("chain_pick_p95_mm", p95_pick)
    section.goals.append(
        Goal(
            f"vision pick with the calibrated hand-eye and intrinsics: p95 <= {GOAL_PICK_MM} mm",
            f"p95 {p95_pick:.3f} mm over {len(grasped)} picks, {failed} failed",
            failed == 0 and p95_pick <= GOAL_PICK_MM,
        )
    )
    chain.caption = (
        "Commissioned from fx = fy = 1350 px and a mount 4 mm / 0.6 deg off (the truth: "
        "1400 px, xyz (70, 0, -100) mm); the pick cell's arm has the same repeatability."
    )
    section.tables.append(chain)
    section.intro = __doc__.split("\n\n")[0].replace("\n", " ") if __doc__ else ""
    section.notes.append(
        "σ is the refinement's standard deviation from the corners' reprojection alone; the "
        "arm's repeatability is not in that model, so σ is several times smaller than the "
        "true error: the per-pose translation residuals and the AX=XB loop (a few tenths of a "
        "millimetre here) are the figures that show the arm's share."
    )

    def plot(directory: Path) -> list[Path]:
        plt = pyplot()
        if plt is None:
            return []
        fig, axes = plt.subplots(1, 2, figsize=(11, 4))
        x = np.arange(n)
        for ax, values, goal, unit, title in (
            (axes[0], t_errors, GOAL_T_MM, "mm", "translation"),
            (axes[1], r_errors, GOAL_R_DEG, "deg", "rotation"),
        ):
            ax.bar(x, values, 0.6)
            ax.axhline(goal, color="grey", linestyle="--")
            ax.set_xlabel("seed")
            ax.set_ylabel(f"error [{unit}]")
            ax.set_title(f"tool_from_camera {title} error (goal: dashed)")
            ax.grid(True, alpha=0.3)
        return [save(fig, directory / "hand_eye.png")]

    section.plot = plot
    return section
