"""Regenerate the simulated images of the golden cases and their expected.yaml from ground truth.

    .venv/bin/python test_inspections/generate.py              # every case
    .venv/bin/python test_inspections/generate.py qc qr_pose   # some of them

Everything is deterministic (fixed seeds; the same calls give the same images, see
simulation/README.md). Expected results come from the simulation's ground truth, never from
the inspections' own output: cap centres from ``frame.truth.features``, QR corners and
``camera_from_qr`` from ``frame.truth.qr_codes``, dark fractions from the label image, verdicts
from what is in the scene. Images are cropped or downscaled to keep the PNGs small; the
coordinates in expected.yaml are those of the stored image.

The real-photograph case (qr_real_photos) takes its payloads from ../shared/data/qr_real when
that directory is present; its images are never copied here.
"""

from __future__ import annotations

import argparse
import json
import sys
from collections.abc import Callable
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import yaml
from numpy.typing import NDArray

HERE = Path(__file__).resolve().parent
REPO = HERE.parent
sys.path.insert(0, str(REPO))

from geometry import invert_transform, transform_from_xyz_rpy  # noqa: E402
from simulation import SimCell, scene_from_text  # noqa: E402
from vision_server.commands.golden import expected_yaml  # noqa: E402

SCENE = REPO / "examples" / "scenes" / "grundfos_cell.yaml"
QR_REAL = REPO.parent / "shared" / "data" / "qr_real"
HEADER = (
    "# Written by test_inspections/generate.py from the simulation's ground truth.\n"
    "# `vision-server test-inspections --update` rewrites it and keeps tolerances and notes.\n"
)

Array = NDArray[Any]
Entries = dict[str, dict[str, Any]]


def scene_text(edit: Callable[[dict[str, Any]], None] | None = None) -> str:
    data = yaml.safe_load(SCENE.read_text(encoding="utf-8"))
    if edit is not None:
        edit(data)
    return yaml.safe_dump(data, sort_keys=False)


def make_cell(seed: int, edit: Callable[[dict[str, Any]], None] | None = None) -> SimCell:
    return SimCell(scene_from_text(scene_text(edit), source="generate.py"), seed=seed)


def camera_spec(data: dict[str, Any], name: str) -> dict[str, Any]:
    spec: dict[str, Any] = next(c for c in data["cameras"] if c["name"] == name)
    return spec


def r2(values: Any) -> list[Any]:
    return [[round(float(x), 2) for x in row] for row in np.asarray(values)]


def write_png(path: Path, image: Array) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    ok, buf = cv2.imencode(".png", image, [cv2.IMWRITE_PNG_COMPRESSION, 9])
    assert ok
    path.write_bytes(buf.tobytes())


def write_expected(case: str, entries: Entries, defaults: dict[str, Any]) -> None:
    (HERE / case).mkdir(parents=True, exist_ok=True)
    (HERE / case / "expected.yaml").write_text(
        expected_yaml(HEADER, defaults, entries), encoding="utf-8"
    )


# --------------------------------------------------------------------------- tool camera: caps

SEARCH_RPY = [np.pi, 0.0, 0.0]


def tool_frame(x: float, seed: int, edit: Callable[[dict[str, Any]], None] | None = None) -> Any:
    cell = make_cell(seed, edit)
    cell.robot.move_linear(transform_from_xyz_rpy([x, -0.55, 0.275], SEARCH_RPY))
    return cell.render("tool_camera")


def half(uv: Array) -> Array:
    """Pixel coordinates after a 2x area downscale (pixel centres at integers)."""
    out: Array = (np.asarray(uv, float) + 0.5) / 2.0 - 0.5
    return out


def dim(data: dict[str, Any]) -> None:
    data["light"] = {"direction": [0.3, 0.2, -1.0], "ambient": 0.16, "diffuse": 0.2}


def blurred(data: dict[str, Any]) -> None:
    camera_spec(data, "tool_camera")["blur_sigma_px"] = 3.0


def caps_case() -> None:
    """locate/circle: rotor caps seen by the tool camera, stored at half size (512x384)."""
    views: list[tuple[str, float, int, Callable[[dict[str, Any]], None] | None, str]] = [
        ("cap1_centred.png", 0.08, 11, None, "cap_1 near the image centre"),
        ("two_caps.png", 0.155, 12, None, "cap_1 and cap_2"),
        ("cap_at_edge.png", 0.30, 13, None, "caps cut by the image border (partly out of view)"),
        ("low_contrast.png", 0.155, 14, dim, "dim light: caps ~55, belt ~15 grey levels"),
        ("blurred.png", 0.08, 15, blurred, "optical blur sigma 3 px (full size)"),
        ("empty_belt.png", 0.75, 16, None, "nothing there: the empty end of the belt"),
    ]
    entries: Entries = {}
    for name, x, seed, edit, note in views:
        frame = tool_frame(x, seed, edit)
        image = cv2.resize(frame.color, (512, 384), interpolation=cv2.INTER_AREA)
        write_png(HERE / "cap_locate_circle" / "images" / name, image)
        whole, cut = [], 0
        for fname, truth in frame.truth.features.items():
            if not fname.startswith("cap_") or not truth.in_image:
                continue
            u, v = truth.uv
            if 90 < u < 1024 - 90 and 90 < v < 768 - 90:  # the disc wholly inside the image
                whole.append(half(truth.uv))
            else:
                cut += 1
        entry: dict[str, Any] = {"verdict": "pass" if whole else "fail", "note": note}
        if not cut:
            entry["count"] = len(whole)
        entry["features"] = r2(sorted(whole, key=lambda p: p[0]))
        entries[name] = entry
    write_expected("cap_locate_circle", entries, {"tolerance_px": 1.0})


# --------------------------------------------------------------------------- QC camera: magnet

QC_CROP = (352, 130, 320, 240)  # u, v, width, height of the stored window of the QC image


def slot_pose(cell: SimCell, dx: float = 0.0, dy: float = 0.0, yaw: float = 0.0) -> Array:
    core = cell.world.part_pose("rotor_core")[:3, 3]
    z = cell.world.parts["magnet"].world_from_part[2, 3]
    pose: Array = transform_from_xyz_rpy([core[0] + 0.05 + dx, core[1] + dy, z], [0, 0, yaw])
    return pose


def occluder(data: dict[str, Any]) -> None:
    """A gripper finger (a bright bar) 5 cm above the outer half of the magnet's slot."""
    data["boxes"].append(
        {
            "name": "finger",
            "pose": {"xyz": [0.15 + 0.05 + 0.016, 0.65, 0.85], "rpy": [0.0, 0.0, 0.0]},
            "size": [0.02, 0.06, 0.01],
            "color": 215,
        }
    )


def qc_noisy(data: dict[str, Any]) -> None:
    """Light at 55 %: table ~93, core ~64, magnet ~22 grey levels; noise 2.5."""
    data["light"] = {"direction": [0.3, 0.2, -1.0], "ambient": 0.25, "diffuse": 0.3}
    camera_spec(data, "qc_camera")["noise_sigma"] = 2.5


# (file, seed, scene edit, magnet placement (None: left in its feeder), in the slot?, note)
QC_VIEWS: list[tuple[str, int, Any, tuple[float, float, float] | None, bool, str]] = [
    ("in_slot.png", 21, None, (0.0, 0.0, 0.0), True, "magnet in its slot"),
    ("in_slot_2.png", 22, None, (0.0015, -0.001, 0.04), True, "in its slot, 2 mm / 2 deg off"),
    ("rotated.png", 23, None, (0.0, 0.0, 0.6), True, "in the slot, turned 0.6 rad"),
    ("rotated_neg.png", 24, None, (0.0, 0.01, -1.1), True, "beside the slot, turned -1.1 rad"),
    ("beside_slot.png", 25, None, (0.0, 0.03, 0.0), False, "on the table 3 cm beside the slot"),
    ("occluded.png", 26, occluder, (0.0, 0.0, 0.0), True, "in the slot, outer half hidden"),
    ("low_contrast.png", 27, qc_noisy, (0.0, 0.0, 0.0), True, "dim light, more noise"),
    ("low_contrast_empty.png", 28, qc_noisy, None, False, "dim light, slot empty"),
    ("empty.png", 29, None, None, False, "nothing there: the magnet is still in its feeder"),
]


def qc_frames() -> dict[str, tuple[Any, bool, str]]:
    out = {}
    for name, seed, edit, placement, in_slot, note in QC_VIEWS:
        cell = make_cell(seed, edit)
        if placement is not None:
            cell.world.parts["magnet"].world_from_part = slot_pose(cell, *placement)
        out[name] = (cell.render("qc_camera"), in_slot, note)
    return out


def crop(image: Array, window: tuple[int, int, int, int]) -> Array:
    u, v, w, h = window
    return np.ascontiguousarray(image[v : v + h, u : u + w])


def magnet_in_crop(frame: Any) -> tuple[Array, bool]:
    truth = frame.truth.features["magnet.top_centre"]
    uv = np.asarray(truth.uv) - QC_CROP[:2]
    inside = bool(truth.visible) and 0 <= uv[0] < QC_CROP[2] and 0 <= uv[1] < QC_CROP[3]
    return uv, inside


def magnet_template(path: Path) -> None:
    """The integrator's template: the magnet on the bare table (3 cm beside its slot, away
    from the core) in one reference image, shifted by a sub-pixel amount first so that the
    magnet's centre is the template's centre."""
    cell = make_cell(20)
    cell.world.parts["magnet"].world_from_part = slot_pose(cell, dy=-0.03)
    frame = cell.render("qc_camera")
    u, v = frame.truth.features["magnet.top_centre"].uv
    w, h = 75, 75  # square: with a rotation search only the inscribed disc is matched
    u0, v0 = int(round(u)) - w // 2, int(round(v)) - h // 2
    shift = np.float32([[1, 0, (u0 + (w - 1) / 2) - u], [0, 1, (v0 + (h - 1) / 2) - v]])
    moved = cv2.warpAffine(frame.color, shift, frame.color.shape[::-1], flags=cv2.INTER_LINEAR)
    write_png(path, moved[v0 : v0 + h, u0 : u0 + w])


def qc_cases() -> None:
    """locate/template, locate/blob and presence on one pool of QC images (qc_images/)."""
    frames = qc_frames()
    magnet_template(HERE / "magnet_locate_template" / "magnet_template.png")
    template: Entries = {}
    blob: Entries = {}
    presence: Entries = {}
    roi = (137, 100, 46, 56)  # the slot, in the stored window (= [489, 230, 46, 56] full size)
    for name, (frame, in_slot, note) in frames.items():
        write_png(HERE / "qc_images" / name, crop(frame.color, QC_CROP))
        uv, inside = magnet_in_crop(frame)
        features = r2([uv]) if inside else []
        mask = crop(frame.truth.mask("magnet"), QC_CROP)
        u, v, w, h = roi
        hidden = name == "occluded.png"
        template[name] = {
            "verdict": "pass" if inside else "fail",
            "count": 1 if inside else 0,
            "features": features,
            "note": note,
        }
        if not hidden:  # a blob's centroid is that of the visible part only
            blob[name] = dict(template[name])
        presence[name] = {
            "verdict": "pass" if in_slot else "fail",
            "value": round(float(mask[v : v + h, u : u + w].mean()), 4),
            "note": note,
        }
    # 1.5 px: the 8 mm tall magnet's side faces, seen in perspective, move its silhouette up
    # to ~0.8 px from the top face's centre (the truth), differently at each place and angle.
    write_expected("magnet_locate_template", template, {"tolerance_px": 1.5})
    write_expected("magnet_locate_blob", blob, {"tolerance_px": 1.5})
    write_expected("magnet_presence", presence, {"tolerance_value": 0.05})
    # The example cell's own magnet_check, on full-size images blacked out beyond its ROI.
    example: Entries = {}
    keep = (466, 216, 90, 100)  # around the example's ROI [486, 236, 50, 60]
    for name in ("in_slot.png", "occluded.png", "beside_slot.png", "empty.png"):
        frame, in_slot, note = frames[name]
        image = np.zeros_like(frame.color)
        ku, kv, kw, kh = keep
        image[kv : kv + kh, ku : ku + kw] = frame.color[kv : kv + kh, ku : ku + kw]
        write_png(HERE / "example_cell_magnet_check" / "images" / name, image)
        mask = frame.truth.mask("magnet")[236:296, 486:536]
        example[name] = {
            "verdict": "pass" if in_slot else "fail",
            "value": round(float(mask.mean()), 4),
            "note": note,
        }
    write_expected("example_cell_magnet_check", example, {"tolerance_value": 0.05})


# --------------------------------------------------------------------------- RGB-D camera: QR

BOARD = "qr_station"
TEXT = "cellvision:station-1"


def look_at(eye: Array, target: Array, roll: float = 0.0) -> Array:
    """world_from_camera (OpenCV axes) at ``eye`` looking at ``target``, world z up on the
    image (before ``roll``, clockwise on screen)."""
    z = target - eye
    z = z / np.linalg.norm(z)
    y = np.array([0.0, 0.0, -1.0])
    y = y - (y @ z) * z
    y = y / np.linalg.norm(y)
    x = np.cross(y, z)
    c, s = np.cos(roll), np.sin(roll)
    x, y = c * x + s * y, -s * x + c * y
    pose = np.eye(4)
    pose[:3, :3] = np.column_stack([x, y, z])
    pose[:3, 3] = eye
    return pose


def rgbd_frames(
    cell: SimCell, world_from_camera: Array, depth_frames: int
) -> tuple[Any, list[Array]]:
    """Put the tool so that the rgbd camera sits at ``world_from_camera``; one colour frame
    and ``depth_frames`` depth frames."""
    tool_from_camera = cell.scene.camera("rgbd").pose
    world_from_tool = world_from_camera @ invert_transform(tool_from_camera)
    cell.world.base_from_tool = invert_transform(cell.world.world_from_base) @ world_from_tool
    first = cell.render("rgbd")
    depth = [first.depth] + [cell.render("rgbd").depth for _ in range(depth_frames - 1)]
    return first, depth


def board_view(
    cell: SimCell, distance: float, *, tilt: float = 0.0, roll: float = 0.0, aim: float = 0.0
) -> Array:
    board = cell.scene.qr_boards[0].world_from_board
    centre = board[:3, 3]
    normal = board[:3, 2]  # out of the print, towards the robot
    side = np.cross(np.array([0.0, 0.0, 1.0]), normal)
    direction = np.cos(tilt) * normal + np.sin(tilt) * side
    eye = centre + distance * direction
    return look_at(eye, centre + aim * side, roll)


def window_around(uv: Array, size: tuple[int, int], image: tuple[int, int]) -> tuple[int, ...]:
    w, h = size
    centre = np.asarray(uv).mean(axis=0)
    u = int(np.clip(round(centre[0] - w / 2), 0, image[0] - w))
    v = int(np.clip(round(centre[1] - h / 2), 0, image[1] - h))
    return u, v, w, h


def qr_case() -> None:
    """qr: the station's code seen by the RGB-D camera's colour image, stored as a grey window
    around the code (the inspection reads grey)."""
    blur = lambda data: camera_spec(data, "rgbd").update(blur_sigma_px=1.2)  # noqa: E731
    views: list[tuple[str, int, Any, dict[str, float], tuple[int, int], str]] = [
        ("near_0.6m.png", 31, None, {"distance": 0.6}, (240, 240), "0.6 m, frontal"),
        ("mid_1.0m.png", 32, None, {"distance": 1.0}, (160, 160), "1.0 m, frontal"),
        ("far_1.6m.png", 33, None, {"distance": 1.6}, (128, 128), "1.6 m (~57 px code)"),
        ("far_2.2m.png", 34, None, {"distance": 2.2}, (128, 128), "2.2 m (~41 px code)"),
        ("rotated_40deg.png", 35, None, {"distance": 0.9, "roll": 0.7}, (200, 200), "roll 40°"),
        ("upside_down.png", 36, None, {"distance": 0.9, "roll": 3.0}, (200, 200), "roll 172°"),
        ("tilted_35deg.png", 37, None, {"distance": 0.9, "tilt": 0.6}, (200, 200), "35° oblique"),
        ("blurred.png", 38, blur, {"distance": 0.9}, (200, 200), "optical blur sigma 1.2 px"),
        ("nothing.png", 39, None, {"distance": 0.9, "aim": 0.45}, (200, 200), "panel, no code"),
    ]
    entries: Entries = {}
    for name, seed, edit, view, size, note in views:
        cell = make_cell(seed, edit)
        frame, _ = rgbd_frames(cell, board_view(cell, **view), 1)
        truth = frame.truth.qr_codes[BOARD]
        corners = truth.corners_uv
        gray = cv2.cvtColor(frame.color, cv2.COLOR_BGR2GRAY)
        if name == "nothing.png":
            window = window_around(np.array([[320.0, 240.0]]), size, (640, 480))
        else:
            window = window_around(corners, size, (640, 480))
        write_png(HERE / "station_qr" / "images" / name, crop(gray, window))
        inside = corners - np.asarray(window[:2], float)
        visible = bool(
            truth.visible and (inside >= 0).all() and (inside < np.asarray(size) - 1).all()
        )
        entry: dict[str, Any] = {"verdict": "pass" if visible else "fail", "note": note}
        if visible:
            entry["text"] = truth.text
            entry["corners"] = r2(inside)
        entries[name] = entry
    write_expected("station_qr", entries, {"tolerance_px": 1.0})


def qr_pose_case() -> None:
    """qr_pose: colour window + 3 registered depth frames; the case's intrinsics are the
    Xtion's with the principal point moved by the window's origin."""
    views = [
        ("frontal_0.8m.png", 41, {"distance": 0.8}, "0.8 m, frontal"),
        ("oblique_1.1m.png", 42, {"distance": 1.1, "tilt": 0.45, "roll": 0.3}, "1.1 m, 26° off"),
        ("nothing.png", 43, {"distance": 0.9, "aim": 0.45}, "the panel beside the code"),
    ]
    size = (224, 192)
    window_origin = None
    entries: Entries = {}
    for name, seed, view, note in views:
        cell = make_cell(seed)
        frame, depth = rgbd_frames(cell, board_view(cell, **view), 3)
        truth = frame.truth.qr_codes[BOARD]
        window = window_around(np.array([[320.0, 240.0]]), size, (640, 480))
        window_origin = window[:2]
        stem = name[:-4]
        folder = HERE / "station_pose" / "images"
        write_png(folder / name, crop(frame.color, window))
        for index, d in enumerate(depth):
            write_png(folder / f"{stem}.depth{index}.png", crop(d, window))
        inside = truth.corners_uv - np.asarray(window[:2], float)
        visible = bool((inside >= 0).all() and (inside < np.asarray(size) - 1).all())
        entry: dict[str, Any] = {"verdict": "pass" if visible else "fail", "note": note}
        if visible:
            entry["text"] = truth.text
            entry["corners"] = r2(inside)
            entry["camera_from_qr"] = [
                [round(float(x), 6) for x in row] for row in truth.camera_from_qr
            ]
        entries[name] = entry
    write_expected(
        # 1 mm and 0.2° (the design's calibration bar); measured: < 0.1 mm and < 0.07°.
        "station_pose",
        entries,
        {"tolerance_px": 1.0, "tolerance_m": 0.001, "tolerance_rad": 0.0035},
    )
    intr = make_cell(41).scene.camera("rgbd").intrinsics
    assert window_origin is not None
    print(
        "station_pose window",
        window_origin,
        "size",
        size,
        "cx, cy =",
        intr.cx - window_origin[0],
        intr.cy - window_origin[1],
    )


# --------------------------------------------------------------------------- calibration board

BOARD_SCENE = REPO / "examples" / "scenes" / "intrinsics_cell.yaml"


def board_case() -> None:
    """calibration_board: the tool camera's planned views of the ChArUco board, half size;
    the expected count is the number of inner corners whose true projection is in the image
    (every view here shows the whole board), none where the camera looks past the board."""
    from robot_client.commissioning.views import plan_tool_views
    from simulation import load_scene
    from simulation.calibration_board import spec_from_opencv

    scene = load_scene(BOARD_SCENE)
    board = scene.calibration_boards[0]
    camera = scene.camera("tool_camera")
    base_from_board = (
        invert_transform(scene.robot.world_from_base)
        @ board.world_from_board
        @ spec_from_opencv(board)
    )
    poses = plan_tool_views(
        base_from_board, camera.pose, board.size_m, fx_px=1400.0, image_width_px=1024
    )
    aside = poses[0].copy()
    aside[:3, 3] += np.array([0.0, 0.45, 0.0])  # the camera looks at the table beside the board
    views = [
        ("frontal.png", poses[0], "frontal, the board fills 0.8 of the width"),
        ("tilted_30deg.png", poses[5], "tilted 30° about the board's x axis"),
        ("diagonal_rolled.png", poses[9], "tilted 21° about both axes, rolled 15°"),
        ("tilted_y_30deg.png", poses[7], "tilted 30° about the board's y axis"),
        ("nothing.png", aside, "the table beside the board"),
    ]
    columns, rows = board.columns - 1, board.rows - 1
    cols_idx, rows_idx = np.meshgrid(np.arange(columns), np.arange(rows))
    corners_board = np.stack(
        [
            (cols_idx.ravel() + 1) * board.square_m,
            (rows_idx.ravel() + 1) * board.square_m,
            np.zeros(columns * rows),
        ],
        axis=1,
    )
    entries: Entries = {}
    for seed, (name, pose, note) in enumerate(views, start=51):
        cell = SimCell(scene, seed=seed)
        cell.robot.move_linear(pose)
        frame = cell.render("tool_camera")
        camera_from_board = (
            invert_transform(cell.world_from_camera("tool_camera"))
            @ board.world_from_board
            @ spec_from_opencv(board)
        )
        uv = camera.intrinsics.project(
            corners_board @ camera_from_board[:3, :3].T + camera_from_board[:3, 3]
        )
        inside = int(np.sum((uv >= 0).all(axis=1) & (uv[:, 0] < 1023) & (uv[:, 1] < 767)))
        small = cv2.resize(frame.color, (512, 384), interpolation=cv2.INTER_AREA)
        write_png(HERE / "commissioning_board" / "images" / name, small)
        entry: dict[str, Any] = {"verdict": "pass" if inside else "fail", "note": note}
        if inside:
            entry["count"] = inside
        entries[name] = entry
    write_expected("commissioning_board", entries, {})


# --------------------------------------------------------------------------- codes

GS, RS, EOT = "\x1d", "\x1e", "\x04"
LABEL_DM = f"[)>{RS}06{GS}P12345{RS}{EOT}"  # ISO/IEC 15434 format 06: separators in the payload
LABEL_128 = f"ABC{GS}4711"


def code_symbol(fmt_name: str, text: str, scale: int, border: int) -> tuple[Array, Array]:
    """A white image with the symbol written by zxing-cpp, and the symbol's corners in symbol
    order (the centres of its outermost module pixels, as the decoder reports them)."""
    import zxingcpp

    symbol = zxingcpp.create_barcode(text, getattr(zxingcpp.BarcodeFormat, fmt_name))
    bare = np.asarray(zxingcpp.write_barcode_to_image(symbol, scale=scale, add_quiet_zones=False))
    img = cv2.copyMakeBorder(bare, border, border, border, border, cv2.BORDER_CONSTANT, value=255)
    h, w = bare.shape[:2]
    lo_u, lo_v, hi_u, hi_v = border, border, border + w - 1, border + h - 1
    corners = np.array([[lo_u, lo_v], [hi_u, lo_v], [hi_u, hi_v], [lo_u, hi_v]], float)
    return np.asarray(img, np.uint8), corners


def codes_case() -> None:
    """code: DataMatrix and Code 128 labels written by zxing-cpp's encoder (payloads with GS1 /
    ISO 15434 separators), upright, turned, inverted, blurred, a wrong payload and none."""
    entries: Entries = {}
    out = HERE / "label_codes" / "images"
    dm, dm_corners = code_symbol("DataMatrix", LABEL_DM, 5, 30)
    entries["datamatrix.png"] = {"verdict": "pass", "note": "upright, 5 px modules"}
    entries["datamatrix.png"].update(text=LABEL_DM, corners=r2(dm_corners))
    write_png(out / "datamatrix.png", dm)
    # np.rot90 turns the image a quarter counter-clockwise: (u, v) -> (v, W - 1 - u)
    turned = np.ascontiguousarray(np.rot90(dm))
    w = dm.shape[1]
    turned_corners = np.stack([dm_corners[:, 1], w - 1 - dm_corners[:, 0]], axis=1)
    entries["datamatrix_turned.png"] = {"verdict": "pass", "note": "turned 90°"}
    entries["datamatrix_turned.png"].update(text=LABEL_DM, corners=r2(turned_corners))
    write_png(out / "datamatrix_turned.png", turned)
    entries["datamatrix_inverted.png"] = {"verdict": "pass", "note": "light on dark"}
    entries["datamatrix_inverted.png"].update(text=LABEL_DM, corners=r2(dm_corners))
    write_png(out / "datamatrix_inverted.png", 255 - dm)
    wrong, _ = code_symbol("DataMatrix", LABEL_DM.replace("P12345", "Q12345"), 5, 30)
    entries["wrong_payload.png"] = {"verdict": "fail", "note": "reads, but not the expected"}
    write_png(out / "wrong_payload.png", wrong)
    bar, _ = code_symbol("Code128", LABEL_128, 3, 30)
    # a 1D code's corners are the ends of the band the decoder scanned: only the text is known
    entries["code128.png"] = {"verdict": "pass", "note": "Code 128 with a GS", "text": LABEL_128}
    write_png(out / "code128.png", bar)
    soft = cv2.GaussianBlur(bar, (0, 0), 1.0)
    entries["code128_blurred.png"] = {"verdict": "pass", "note": "blur sigma 1 px"}
    entries["code128_blurred.png"]["text"] = LABEL_128
    write_png(out / "code128_blurred.png", soft)
    rng = np.random.default_rng(7)
    ramp = np.linspace(60, 200, 240)[None, :] + rng.normal(0, 6, (180, 240))
    entries["nothing.png"] = {"verdict": "fail", "note": "shaded, noisy, no code"}
    write_png(out / "nothing.png", np.clip(ramp, 0, 255).astype(np.uint8))
    # zxing-cpp's corners are whole-pixel estimates of the outermost modules: up to 1 px each way
    write_expected("label_codes", entries, {"tolerance_px": 1.5})


# --------------------------------------------------------------------------- caliper: a bracket

BRACKET_CROP = (600, 400, 240, 180)  # u, v, width, height of the stored window (tool camera)
BRACKET_ANGLE = 0.2  # rad: the direction the bracket's width runs in, from plane x towards y


def bracket(width_mm: float, hole_mm: float, shift_mm: float = 0.0) -> Any:
    """A flat bracket (a bar ``width_mm`` wide) with a round hole, seen by the tool camera
    350 mm away, centred on the stored window's centre (moved ``shift_mm`` along its length)."""
    from simulation.flat_parts import bar, disc, plane_point
    from simulation.scene import camera_preset

    camera, _, _ = camera_preset("dmk31bf03")
    u0, v0, w, h = BRACKET_CROP
    cx, cy = plane_point(camera, 350.0, (u0 + w / 2 - 0.5, v0 + h / 2 - 0.5))
    along = (-np.sin(BRACKET_ANGLE) * shift_mm, np.cos(BRACKET_ANGLE) * shift_mm)
    centre = (cx + along[0], cy + along[1])
    plate, hole = bar(centre, width_mm, BRACKET_ANGLE), disc(centre, hole_mm)
    return camera, lambda x, y: plate(x, y) & ~hole(x, y)


def caliper_case() -> None:
    """caliper in mm: a bracket's width and its hole's diameter against tolerances; the
    expected value (the width) is the rendered part's, exactly."""
    from simulation.flat_parts import render_flat_part

    out = HERE / "caliper_bracket" / "images"
    entries: Entries = {}
    u0, v0, w, h = BRACKET_CROP
    cases = [
        ("nominal.png", 12.0, 6.0, {}, "pass", "12.00 mm wide, 6.00 mm hole"),
        ("wide.png", 12.3, 6.0, {}, "fail", "12.30 mm wide: over max 12.1"),
        ("small_hole.png", 12.0, 5.8, {}, "fail", "hole 5.80 mm: under min 5.95"),
        ("moved_along.png", 11.95, 6.02, {"shift": 1.0}, "pass", "moved 1 mm along its length"),
        ("blurred.png", 12.05, 5.98, {"blur_sigma_px": 1.6}, "pass", "defocus blur sigma 1.6 px"),
        ("dim.png", 11.92, 6.0, {"ground": 70.0, "part": 120.0}, "pass", "dim: 50 grey levels"),
    ]
    for seed, (file, width_mm, hole_mm, extra, verdict, note) in enumerate(cases):
        camera, shape = bracket(width_mm, hole_mm, float(extra.pop("shift", 0.0)))
        image = render_flat_part(camera, 350.0, shape, BRACKET_CROP, seed=seed, **extra)
        write_png(out / file, image[v0 : v0 + h, u0 : u0 + w])
        entries[file] = {"verdict": verdict, "value": round(width_mm, 4), "note": note}
    rng = np.random.default_rng(11)
    empty = 60.0 + rng.normal(0.0, 1.5, (h, w))
    write_png(out / "no_part.png", np.clip(np.rint(empty), 0, 255).astype(np.uint8))
    entries["no_part.png"] = {"verdict": "fail", "note": "nothing there: nothing measured"}
    write_expected("caliper_bracket", entries, {"tolerance_value": 0.02})


# ----------------------------------------------------------------- textured part: template

PART_SEED = 7  # simulation.textured_part.random_part's seed: a 65 px textured part
PART_SIZE = (320, 240)
PartPose = tuple[float, float, float, float]  # u, v, angle, scale
Occluder = tuple[float, float, float, float, float]  # u0, v0, u1, v1, grey


def template_scale_case() -> None:
    """locate/template with a scale and rotation search on a flat textured part whose pose is
    known exactly (simulation.textured_part): nearer and farther (+-10 %), turned, a quarter
    hidden by a dark finger and by a bright one, another part, nothing."""
    from simulation.textured_part import random_part

    part = random_part(PART_SEED)
    case = HERE / "part_locate_template_scaled"
    write_png(case / "part_template.png", part.template())
    entries: Entries = {}
    # name: (poses (u, v, angle, scale), occluders (u0, v0, u1, v1, grey), note)
    scenes: dict[str, tuple[list[PartPose], list[Occluder], str]] = {
        "nominal.png": ([(160.4, 118.7, 0.0, 1.0)], [], "as taught"),
        "nearer.png": ([(150.2, 121.6, 0.12, 1.1)], [], "10 % nearer (larger), turned 0.12 rad"),
        "farther.png": ([(171.7, 112.3, -0.2, 0.9)], [], "10 % farther (smaller), turned -0.2"),
        "finger_dark.png": (
            [(158.3, 120.9, 0.05, 1.04)],
            [(158.3 + 17.0, 40.0, 320.0, 200.0, 25.0)],
            "a quarter hidden by a dark gripper finger, 4 % nearer",
        ),
        "finger_bright.png": (
            [(163.8, 117.4, -0.1, 0.93)],
            [(0.0, 0.0, 320.0, 117.4 - 15.0, 205.0)],
            "a quarter hidden by a bright sheet, 7 % farther",
        ),
        "other_part.png": ([], [], "a different part in its place"),
        "empty.png": ([], [], "nothing there"),
    }
    for name, (poses, occluders, note) in scenes.items():
        if name == "other_part.png":
            image = random_part(PART_SEED + 1).scene(
                [(160.0, 120.0, 0.0, 1.0)], size=PART_SIZE, seed=41
            )
        else:
            image = part.scene(poses, size=PART_SIZE, seed=40 + len(entries), occluders=occluders)
        write_png(case / "images" / name, image)
        entries[name] = {
            "verdict": "pass" if poses else "fail",
            "count": len(poses),
            "features": r2([p[:2] for p in poses]) if poses else [],
            "note": note,
        }
    write_expected("part_locate_template_scaled", entries, {"tolerance_px": 0.2})


# --------------------------------------------------------------------------- real photographs

REAL_SUBSET = [  # 13 of the 179 across the six sets (qrcode-4: blur, glare, tilt)
    "qrcode-1/1.png",
    "qrcode-1/12.png",
    "qrcode-2/1.png",
    "qrcode-2/10.png",
    "qrcode-2/15.png",
    "qrcode-3/02.png",
    "qrcode-3/08.png",
    "qrcode-4/01.png",
    "qrcode-4/09.png",
    "qrcode-4/11.png",
    "qrcode-5/04.png",
    "qrcode-6/2.png",
    "qrcode-6/10.png",
]


def real_case() -> None:
    """qr on real photographs: the payload is the ground truth (no corners are known)."""
    if not (QR_REAL / "manifest.json").is_file():
        print(f"skipping qr_real_photos: {QR_REAL} not found")
        return
    manifest = {
        row["image"]: row["expected_text"]
        for row in json.loads((QR_REAL / "manifest.json").read_text(encoding="utf-8"))
    }
    entries: Entries = {name: {"verdict": "pass", "text": manifest[name]} for name in REAL_SUBSET}
    write_expected("qr_real_photos", entries, {})


# --------------------------------------------------------------------------- job: fixtured plate

PLATE_SIZE = (320, 240)  # width, height of the stored image
PLATE_HOME = (110.0, 120.0)  # the big hole's centre (u, v) when the plate lies where taught
SUPER = 4  # drawn at 4x and area-averaged: anti-aliased edges, sub-pixel positions


def plate_image(
    pose: tuple[float, float, float],
    magnet: tuple[float, float] | None,
    seed: int,
    half_width: float = 40.0,
) -> Array:
    """A bright plate (grey 190) on a dark belt (40) with two through holes: the big one
    (radius 12 px) is the part frame's origin, the small one (radius 7 px) lies 100 px along
    its x axis; a dark magnet (30, 16x16 px) sits centred at ``magnet`` (part-frame pixels;
    None: absent). The plate spans x -30..130 and y -``half_width``..``half_width`` of the part
    frame (drawn, it comes out about 0.4 px wider: the 4x fill covers its boundary pixels).
    ``pose``: the big hole's (u, v) and the x axis's angle in radians (from +u towards +v).
    Defocus blur sigma 0.7 px and noise sigma 2 grey levels (seeded)."""
    u0, v0, angle = pose
    c, s = np.cos(angle), np.sin(angle)

    def hi(x: float, y: float) -> tuple[int, int]:
        u, v = u0 + c * x - s * y, v0 + s * x + c * y
        # pixel centre i of the stored image is 4 i + 1.5 at 4x; 4 fractional bits for cv2
        return int(round((SUPER * u + 1.5) * 16)), int(round((SUPER * v + 1.5) * 16))

    width, height = PLATE_SIZE
    canvas = np.full((height * SUPER, width * SUPER), 40, np.uint8)

    def poly(corners: list[tuple[float, float]], grey: int) -> None:
        pts = np.array([hi(x, y) for x, y in corners], np.int32)
        cv2.fillPoly(canvas, [pts], grey, cv2.LINE_AA, shift=4)

    hw = half_width
    poly([(-30, -hw), (130, -hw), (130, hw), (-30, hw)], 190)
    for (x, y), radius in (((0.0, 0.0), 12.0), ((100.0, 0.0), 7.0)):
        cv2.circle(canvas, hi(x, y), int(round(radius * SUPER * 16)), 40, -1, cv2.LINE_AA, 4)
    if magnet is not None:
        mx, my = magnet
        poly([(mx - 8, my - 8), (mx + 8, my - 8), (mx + 8, my + 8), (mx - 8, my + 8)], 30)
    small = cv2.resize(canvas, (width, height), interpolation=cv2.INTER_AREA).astype(np.float64)
    small = cv2.GaussianBlur(small, (0, 0), 0.7)
    noise = np.random.default_rng(seed).normal(0.0, 2.0, small.shape)
    out: Array = np.clip(np.round(small + noise), 0, 255).astype(np.uint8)
    return out


POCKET = (50.0, 18.0)  # where the magnet belongs, in the part frame (px)

# (file, seed, (du, dv, angle) from the taught pose, magnet in part frame or None, passes, note)
PLATE_VIEWS: list[tuple[str, int, tuple[float, float, float] | None, Any, bool, str]] = [
    ("taught.png", 61, (0.0, 0.0, 0.0), POCKET, True, "where the job was taught"),
    ("moved_a.png", 62, (23.4, -14.7, 0.30), POCKET, True, "moved (23.4, -14.7) px, turned 17 deg"),
    ("moved_b.png", 63, (-17.8, 11.2, -0.42), POCKET, True, "moved (-17.8, 11.2), turned -24 deg"),
    ("moved_c.png", 64, (31.0, 20.5, 0.12), POCKET, True, "moved (31, 20.5) px, turned 7 deg"),
    ("moved_empty.png", 65, (19.0, -9.0, 0.35), None, False, "moved and turned, no magnet"),
    ("moved_beside.png", 66, (-12.0, 15.0, -0.30), (85.0, 18.0), False, "magnet 35 px off"),
    ("no_plate.png", 67, None, None, False, "nothing there: the belt"),
    ("moved_narrow.png", 68, (-21.0, -12.0, 0.38), POCKET, False, "plate 74 px wide, not 80"),
]
PLATE_HALF_WIDTH = {"moved_narrow.png": 37.0}
"""Views of a plate cut too narrow (part-frame px; the others are 40): the caliper step's
width fails there while everything else passes."""


def plate_case() -> None:
    """job: locate the plate's holes, fixture a frame to them, check the magnet's pocket and
    measure the plate's width with a caliper in the part frame."""
    entries: Entries = {}
    for name, seed, move, magnet, passes, note in PLATE_VIEWS:
        if move is None:
            image = np.full(PLATE_SIZE[::-1], 40, np.uint8)
            noise = np.random.default_rng(seed).normal(0.0, 2.0, image.shape)
            image = np.clip(np.round(image + noise), 0, 255).astype(np.uint8)
            entries[name] = {"verdict": "fail", "count": 0, "features": [], "note": note}
        else:
            du, dv, angle = move
            origin = (PLATE_HOME[0] + du, PLATE_HOME[1] + dv)
            half = PLATE_HALF_WIDTH.get(name, 40.0)
            image = plate_image((origin[0], origin[1], angle), magnet, seed, half)
            # two fixtures (translation only, then translation + rotation), both at the big hole
            entries[name] = {
                "verdict": "pass" if passes else "fail",
                "count": 2,
                "features": r2([origin, origin]),
                "note": note,
            }
        write_png(HERE / "fixtured_plate" / "images" / name, image)
    write_expected("fixtured_plate", entries, {"tolerance_px": 0.3})


ANOMALY_CASE = "anomaly_surface"
ANOMALY_PART = 128
"""The part's side in the stored images (px): the synthetic part of the tests, scaled down."""
ANOMALY_ROI = (16, 11, ANOMALY_PART, ANOMALY_PART)
ANOMALY_IMAGE = (160, 150)
ANOMALY_VIEWS: tuple[tuple[str, str | None, int, str], ...] = (
    ("good_a.png", None, 101, "a good part"),
    ("good_b.png", None, 102, "a good part"),
    ("good_c.png", None, 103, "a good part"),
    ("scratch.png", "scratch", 104, "a dark scratch about 20 px long"),
    ("hole.png", "hole", 105, "a drilled hole where there is none"),
    ("stain.png", "stain", 106, "a soft dark stain"),
    ("empty.png", "empty", 107, "no part: the bare belt"),
)


def anomaly_case() -> None:
    """anomaly (method variation): a model trained on 20 good synthetic parts
    (tests/helpers/anomaly_synthetic.py), committed beside the case, judges good parts and
    parts with a scratch, a hole or a stain. Verdicts from what was drawn."""
    sys.path.insert(0, str(REPO / "tests" / "helpers"))
    from anomaly_synthetic import defective_part, good_part

    from vision_server.analysis.anomaly import model_bytes, train_model

    side = (ANOMALY_PART, ANOMALY_PART)

    def small(part: Array) -> Array:
        grey = cv2.cvtColor(part, cv2.COLOR_BGR2GRAY)
        return np.asarray(cv2.resize(grey, side, interpolation=cv2.INTER_AREA), np.uint8)

    def scene(part: Array | None, rng: np.random.Generator) -> Array:
        width, height = ANOMALY_IMAGE
        image = np.full((height, width), 45.0) + rng.normal(0.0, 2.0, (height, width))
        if part is not None:
            u, v, w, h = ANOMALY_ROI
            image[v : v + h, u : u + w] = part
        return np.clip(np.round(image), 0, 255).astype(np.uint8)

    rng = np.random.default_rng(3100)
    training = [small(good_part(rng)) for _ in range(20)]
    model, _ = train_model(training, method="variation", false_reject=0.01, version=1)
    # No training time in the file: the generator writes the same model every run.
    meta = {k: v for k, v in model.meta.items() if k != "trained_at"}
    model = type(model)(
        model.method, model.image_size, model.threshold, model.false_reject, model.scorer, meta
    )
    models = HERE / ANOMALY_CASE / "models"
    models.mkdir(parents=True, exist_ok=True)
    (models / "surface.v1.npz").write_bytes(model_bytes(model))
    entries: Entries = {}
    for name, defect, seed, note in ANOMALY_VIEWS:
        view_rng = np.random.default_rng(seed)
        if defect is None:
            part: Array | None = small(good_part(view_rng))
        elif defect == "empty":
            part = None
        else:
            part = small(defective_part(view_rng, defect)[0])  # type: ignore[arg-type]
        write_png(HERE / ANOMALY_CASE / "images" / name, scene(part, view_rng))
        entries[name] = {"verdict": "pass" if defect is None else "fail", "note": note}
    write_expected(ANOMALY_CASE, entries, {})


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument(
        "cases",
        nargs="*",
        default=[
            "caps",
            "qc",
            "qr",
            "qr_pose",
            "board",
            "codes",
            "caliper",
            "template",
            "real",
            "plate",
            "anomaly",
        ],
        help="caps, qc, qr, qr_pose, board, codes, caliper, template, real, plate, anomaly",
    )
    args = parser.parse_args()
    steps = {
        "caps": caps_case,
        "qc": qc_cases,
        "qr": qr_case,
        "qr_pose": qr_pose_case,
        "board": board_case,
        "codes": codes_case,
        "caliper": caliper_case,
        "template": template_scale_case,
        "real": real_case,
        "plate": plate_case,
        "anomaly": anomaly_case,
    }
    for name in args.cases:
        steps[name]()
    return 0


if __name__ == "__main__":
    sys.exit(main())
