"""``robot-client sensor-check``: the RGB-D tool camera's depth scale error and depth-to-colour
shift, measured by the robot against the QR board.

The robot starts where the camera sees the code (or ``--start`` moves it there first), turns
the camera about the code's centre through ``--views`` views tilted up to ``--tilt-deg`` in
directions spread all round, captures colour and ``--depth-frames`` depth frames at each and
runs the server's ``qr_pose`` inspection (the positional argument: with ``side_m`` and no
depth correction of its own); the fit and the advice are those of ``vision-server
sensor-check``. Exit 0: the sensor is within the limits; 1: it needs a correction (the values
to set are printed); 2: usage, or too few views.
"""

from __future__ import annotations

import argparse
import json
import math
from typing import Any

from rich.console import Console
from rich.markup import escape

from geometry import transform_from_xyz_rpy
from protocol.cli import ExitCode

from ..commissioning.sensor_check import SensorCheck, check_sensor
from .skills import _device_options, _devices

__all__ = ["add_sensor_check_command"]


def _report(check: SensorCheck) -> dict[str, Any]:
    reg = check.registration
    assert reg is not None
    return {
        "views": reg.views,
        "depth_scale": round(reg.scale, 5),
        "depth_scale_std": round(reg.scale_std, 5),
        "depth_shift_px": [round(x, 2) for x in reg.shift_px],
        "depth_shift_std_px": [round(x, 2) if math.isfinite(x) else None for x in reg.shift_std_px],
        "residual_rms": round(reg.residual_rms, 5),
        "skipped": [{"view": label, "reason": why} for label, why in check.skipped],
        "ok": check.ok,
        "verdict": check.advice,
    }


def cmd_sensor_check(args: argparse.Namespace, console: Console) -> int:
    if args.views < 4:
        raise ValueError(
            f"--views must be >= 4 (the shift needs tilts both ways), got {args.views}"
        )
    devices = _devices(args)
    try:
        if args.start is not None:
            devices.robot.move_linear(transform_from_xyz_rpy(args.start[:3], args.start[3:]))
        check = check_sensor(
            devices,
            camera=args.camera,
            inspection=args.inspection,
            views=args.views,
            tilt_deg=args.tilt_deg,
            depth_frames=args.depth_frames,
            corner_bias_px=args.corner_bias_px,
            progress=None
            if args.json
            else lambda message, _: console.print(escape(f"  {message}")),
        )
    finally:
        devices.close()
    report = _report(check)
    if args.json:
        print(json.dumps(report))
    else:
        for label, why in check.skipped:
            console.print(escape(f"not taken: {label}: {why}"), soft_wrap=True)
        for key, value in report.items():
            if key != "skipped":
                console.print(escape(f"{key:20} {value}"), soft_wrap=True)
    return int(ExitCode.OK if check.ok else ExitCode.FAILED)


def add_sensor_check_command(sub: Any, common: argparse.ArgumentParser) -> None:
    """Add ``sensor-check`` to the ``robot-client`` subparsers."""
    p = sub.add_parser(
        "sensor-check",
        parents=[common, _device_options()],
        help="measure the RGB-D tool camera's depth scale and shift against the QR board",
    )
    p.add_argument("inspection", help="the server's qr_pose inspection (with side_m)")
    p.add_argument("--camera", required=True, help="the RGB-D camera on the tool")
    p.add_argument("--views", type=int, default=12, help="views to take (default 12)")
    p.add_argument(
        "--tilt-deg", type=float, default=22.0, help="largest tilt off square (default 22)"
    )
    p.add_argument("--depth-frames", type=int, default=5, help="depth frames per view")
    p.add_argument(
        "--corner-bias-px",
        type=float,
        default=0.0,
        help="the qr_pose inspection's corner_bias_px (the detector's bias on the side)",
    )
    p.add_argument(
        "--start",
        type=float,
        nargs=6,
        default=None,
        metavar=("X", "Y", "Z", "ROLL", "PITCH", "YAW"),
        help="move the tool here first (base frame, metres and radians)",
    )
    p.set_defaults(func=cmd_sensor_check, sync=True)
