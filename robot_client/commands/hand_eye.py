"""``robot-client calibrate-hand-eye``: where a camera sits on the tool or in the cell, from
views of a board.

Eye-in-hand (``--camera`` a tool camera): the robot starts where the camera sees the board; the
command plans 15 poses around the board. Eye-to-hand (``--camera`` a fixed camera): the board
is bolted to the flange and the robot starts where the camera sees it; the command plans 15
poses that show the board to the camera. Either way the poses are a spread of tilts and rolls,
reachability and visibility checked (skipped poses are named with the reason); the robot moves
through them, the server's ``calibration_board`` inspection (the positional argument) finds the
corners, and the robot comes back. It solves ``tool_from_camera`` or ``base_from_camera`` (and
the board on the flange) (closed form, then Levenberg-Marquardt on every corner's reprojection)
and prints the result with the residuals per pose, the AX=XB loop consistency, the standard
deviations and the verdict (good / check / redo, with the reason). After the user confirms
(``--yes`` for scripts) the calibration goes into the teach store (``--store``), record
``hand_eye/CAMERA``, where vision pick, QR calibration and quality control read it. A
``redo`` verdict is never stored and exits 1.

The intrinsics the solution is made with: the server camera's in ``--config FILE`` (as
``calibrate-intrinsics`` wrote them), else the robot's own camera description. They are
stored with the pose, which is right only with them.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path
from typing import Any

import yaml
from rich.console import Console
from rich.markup import escape
from rich.table import Table

from geometry import CameraIntrinsics, xyz_rpy_from_transform
from protocol.cli import ExitCode

from ..commissioning import HandEyeResult, solve_hand_eye
from ..commissioning.hand_eye_collect import HandEyeCollected, collect_hand_eye_views
from ..commissioning.hand_eye_noise import DEFAULT_REPEATABILITY, Repeatability
from ..skills.camera_mounts import _intrinsics_from_yaml, hand_eye_record
from .commission import server_camera
from .skills import _device_options, _devices, _store, _store_options

__all__ = ["add_hand_eye_command"]

_POSE_NAME = {"eye_in_hand": "tool_from_camera", "eye_to_hand": "base_from_camera"}


def _config_intrinsics(path: Path, camera: str) -> CameraIntrinsics:
    """The ``intrinsics`` of ``camera`` in the server's configuration file ``path``."""
    try:
        doc = yaml.safe_load(path.read_text(encoding="utf-8"))
    except (OSError, yaml.YAMLError) as exc:
        raise ValueError(f"{path}: cannot read the configuration: {exc}") from None
    cameras = doc.get("cameras") if isinstance(doc, dict) else None
    entry = cameras.get(camera) if isinstance(cameras, dict) else None
    if not isinstance(entry, dict) or entry.get("intrinsics") is None:
        raise ValueError(f"{path}: camera {camera!r} has no intrinsics (cameras.{camera})")
    try:
        return _intrinsics_from_yaml(entry["intrinsics"])
    except ValueError as exc:
        raise ValueError(f"{path}: cameras.{camera}.{exc}") from None


def _figures(result: HandEyeResult, collected: HandEyeCollected) -> dict[str, Any]:
    """The residuals as plain values (metres, radians, pixels), for the store and --json."""
    return {
        "rms_px": round(result.rms_px, 4),
        "loop_translation_m": round(result.loop_translation_m, 7),
        "loop_rotation_rad": round(result.loop_rotation_rad, 7),
        "sigma_translation_m": round(result.sigma_translation_m, 7),
        "sigma_rotation_rad": round(result.sigma_rotation_rad, 7),
        "expected": {
            "corner_noise_px": round(result.expected.corner_noise_px, 4),
            "rms_px": round(result.expected.rms_px, 4),
            "loop_translation_m": round(result.expected.loop_translation_m, 7),
            "loop_rotation_rad": round(result.expected.loop_rotation_rad, 7),
        },
        "board": collected.board,
        "poses": [
            {
                "pose": collected.labels[v.index],
                "translation_m": round(v.translation_m, 7),
                "rotation_rad": round(v.rotation_rad, 7),
                "rms_px": round(v.rms_px, 4),
            }
            for v in result.views
        ],
        "skipped": [{"pose": label, "reason": why} for label, why in collected.skipped],
    }


def _print_result(
    console: Console, result: HandEyeResult, collected: HandEyeCollected, camera: str
) -> None:
    xyz, rpy = xyz_rpy_from_transform(result.camera)
    console.print(
        f"[bold]{_POSE_NAME[result.setup]}[/] of {escape(camera)} from {len(result.views)} "
        f"poses ({escape(collected.board)}):"
    )
    console.print(
        "  xyz "
        + ", ".join(f"{v * 1000:.3f}" for v in xyz)
        + " mm   rpy "
        + ", ".join(f"{math.degrees(v):.4f}" for v in rpy)
        + " deg"
    )
    # The covariance counts the corners' noise only: it is the solve's statistical spread,
    # not a bound on the error, which the loop below judges.
    console.print(
        f"  statistical spread of the solve (corner noise only, not the error) "
        f"{result.sigma_translation_m * 1000:.3f} mm, "
        f"{math.degrees(result.sigma_rotation_rad):.4f} deg (largest axis)"
    )
    if result.setup == "eye_to_hand":
        board_xyz, board_rpy = xyz_rpy_from_transform(result.board)
        console.print(
            "  board on the flange (tool_from_board, OpenCV board frame): xyz "
            + ", ".join(f"{v * 1000:.3f}" for v in board_xyz)
            + " mm   rpy "
            + ", ".join(f"{math.degrees(v):.4f}" for v in board_rpy)
            + " deg"
        )
    table = Table("pose", "corners", "translation mm", "rotation deg", "RMS px")
    for v in result.views:
        view = collected.views[v.index]
        table.add_row(
            collected.labels[v.index],
            str(len(view.corners_uv)),
            f"{v.translation_m * 1000:.3f}",
            f"{math.degrees(v.rotation_rad):.4f}",
            f"{v.rms_px:.3f}",
        )
    console.print(table)
    for label, reason in collected.skipped:
        console.print(escape(f"not taken: {label}: {reason}"), soft_wrap=True)
    expected = result.expected
    console.print(
        f"reprojection RMS [bold]{result.rms_px:.3f} px[/] (noise explains "
        f"{expected.rms_px:.3f} px); AX=XB loop {result.loop_translation_m * 1000:.3f} mm, "
        f"{math.degrees(result.loop_rotation_rad):.4f} deg (RMS over the pairs of poses; noise "
        f"explains {expected.loop_translation_m * 1000:.3f} mm, "
        f"{math.degrees(expected.loop_rotation_rad):.4f} deg)"
    )
    colour = {"good": "green", "check": "yellow", "redo": "red"}[result.verdict]
    console.print(f"verdict: [{colour}]{result.verdict}[/]")
    for reason in result.reasons:
        console.print(escape(f"  {reason}"), soft_wrap=True)


def _confirmed(
    args: argparse.Namespace, console: Console, camera: str, store: Path, pose_name: str
) -> bool:
    if args.yes:
        return True
    if args.json or not sys.stdin.isatty():
        if not args.json:
            console.print("not stored: confirm with --yes (no terminal to ask at)")
        return False
    answer = console.input(
        f"store this {pose_name} for {escape(camera)!r} in {escape(str(store))}? \\[y/N] "
    )
    return answer.strip().lower() in ("y", "yes")


def cmd_calibrate_hand_eye(args: argparse.Namespace, console: Console) -> int:
    if args.views < 3:
        raise ValueError(f"--views must be >= 3, got {args.views}")
    store = _store(args)
    devices = _devices(args)
    try:
        if args.config:
            intrinsics = _config_intrinsics(Path(args.config), server_camera(devices, args))
        else:
            intrinsics = devices.camera(args.camera).intrinsics
        collected = collect_hand_eye_views(
            devices,
            camera=args.camera,
            inspection=args.inspection,
            intrinsics=intrinsics,
            count=args.views,
            progress=None
            if args.json
            else lambda message, _: console.print(escape(f"  {message}")),
        )
    finally:
        devices.close()
    mm, deg = args.arm_repeatability
    if mm <= 0 or deg <= 0:
        raise ValueError(f"--arm-repeatability must be positive, got {mm} mm {deg} deg")
    result = solve_hand_eye(
        collected.views,
        intrinsics,
        collected.setup,
        repeatability=Repeatability(mm / 1000.0, math.radians(deg)),
    )
    pose_name = _POSE_NAME[result.setup]
    figures = _figures(result, collected)
    xyz, rpy = xyz_rpy_from_transform(result.camera)
    out: dict[str, Any] = {
        "camera": args.camera,
        "setup": result.setup,
        pose_name: {"xyz": [float(v) for v in xyz], "rpy": [float(v) for v in rpy]},
        "verdict": result.verdict,
        "reasons": list(result.reasons),
        **figures,
    }
    if result.setup == "eye_to_hand":
        board_xyz, board_rpy = xyz_rpy_from_transform(result.board)
        out["tool_from_board"] = {
            "xyz": [float(v) for v in board_xyz],
            "rpy": [float(v) for v in board_rpy],
        }
    if not args.json:
        _print_result(console, result, collected, args.camera)
    if result.verdict == "redo":
        out["stored"] = {"stored": False, "reason": "verdict redo"}
        if not args.json:
            console.print("not stored: calibrate again after fixing what the verdict says")
    elif _confirmed(args, console, args.camera, store.path, pose_name):
        record = hand_eye_record(
            args.camera,
            result.setup,
            result.camera,
            intrinsics=intrinsics,
            verdict=result.verdict,
            reasons=result.reasons,
            figures=figures,
        )
        stored = store.put(record)
        out["stored"] = {"stored": True, "store": str(store.path), "revision": stored.revision}
        if not args.json:
            console.print(
                escape(
                    f"stored as {stored.key} (revision {stored.revision}) in {store.path}: "
                    "vision pick, QR calibration and quality control use it from now on"
                )
            )
    else:
        out["stored"] = {"stored": False, "reason": "not confirmed"}
    if args.json:
        print(json.dumps(out))
    return int(ExitCode.FAILED if result.verdict == "redo" else ExitCode.OK)


def add_hand_eye_command(sub: Any, common: argparse.ArgumentParser) -> None:
    """Add ``calibrate-hand-eye`` to the ``robot-client`` subparsers."""
    cal = sub.add_parser(
        "calibrate-hand-eye",
        parents=[common, _device_options(), _store_options()],
        help="calibrate where a camera sits on the tool (tool_from_camera) or in the cell "
        "(base_from_camera, the board on the flange) from board views",
    )
    cal.add_argument("inspection", help="the server's calibration_board inspection")
    cal.add_argument(
        "--camera",
        required=True,
        help="the camera: on the tool (eye-in-hand) or fixed (eye-to-hand, board on the flange)",
    )
    cal.add_argument("--views", type=int, default=15, help="poses to plan (default 15)")
    cal.add_argument(
        "--config",
        default=None,
        metavar="FILE",
        help="take the intrinsics from this server configuration (default: the camera's own)",
    )
    cal.add_argument(
        "--server-camera",
        default=None,
        help="the server camera in --config the images are of (default: the inspection's "
        "camera, which must be --camera's: NAME or NAME without '_camera')",
    )
    cal.add_argument(
        "--arm-repeatability",
        nargs=2,
        type=float,
        metavar=("MM", "DEG"),
        default=(DEFAULT_REPEATABILITY.m * 1000.0, math.degrees(DEFAULT_REPEATABILITY.rad)),
        help="the arm's repeatability (one sigma, mm and deg) the verdict allows for in the "
        "residuals (default 0.03 mm, 0.01 deg)",
    )
    cal.add_argument("--yes", action="store_true", help="store without asking")
    cal.set_defaults(func=cmd_calibrate_hand_eye, sync=True)
