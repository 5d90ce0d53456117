"""``vision-server sensor-check``: the depth camera's scale error and misregistration against
a QR board of known printed side, from saved views (a colour image and its depth frames each),
so that an integrator sees whether the sensor needs its own calibration.

Each view goes through the configured ``qr_pose`` inspection's analysis (its ``side_m``, the
camera's intrinsics, and *no* depth correction); :func:`fit_depth_registration` fits scale and
shift over the views. The board must be tilted in different directions across the views (the
shift shows only through the tilt), e.g. eight views about 20° off square, rotated about it.
"""

from __future__ import annotations

import argparse
import json
import os
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from ..analysis import AnalysisError, fit_depth_registration, qr_pose, registration_advice
from ..config import ConfigError, load_config
from ..inspections import QRPoseInspection

__all__ = ["add_parser", "sensor_check"]


def add_parser(sub: Any, parents: list[argparse.ArgumentParser]) -> None:
    p = sub.add_parser(
        "sensor-check",
        parents=parents,
        help="measure a depth camera's scale error and misregistration against a QR board",
    )
    p.add_argument("inspection", help="a qr_pose inspection with side_m (its camera, its code)")
    p.add_argument(
        "--view",
        nargs="+",
        action="append",
        required=True,
        metavar=("COLOR", "DEPTH"),
        help="one view: a colour image then its 16-bit depth PNGs (mm); repeat per view",
    )
    p.set_defaults(func=sensor_check)


def _read(path: str, flags: int) -> Any:
    image = cv2.imread(path, flags)
    if image is None:
        raise ValueError(f"cannot read image {path!r}")
    return image


def sensor_check(args: argparse.Namespace) -> int:
    """Exit 0: the sensor is within limits; 1: it needs a correction; 2: usage / no views."""
    path = args.config if isinstance(args.config, str) else os.environ.get("CELLVISION_CONFIG")
    if not path:
        print("vision-server sensor-check: give --config FILE (or $CELLVISION_CONFIG)")
        return 2
    try:
        config = load_config(Path(path))
    except (ConfigError, OSError) as exc:
        print(f"vision-server sensor-check: invalid configuration: {exc}")
        return 2
    inspection = next((i for i in config.inspections if i.name == args.inspection), None)
    if not isinstance(inspection, QRPoseInspection) or inspection.side_m is None:
        print(f"vision-server sensor-check: {args.inspection!r} is not a qr_pose with side_m")
        return 2
    intrinsics = config.cameras[inspection.common.camera].intrinsics
    if intrinsics is None:
        print(f"vision-server sensor-check: camera {inspection.common.camera!r} has no intrinsics")
        return 2
    ratios: list[float] = []
    gains: list[list[float]] = []
    sides: list[float] = []
    grids: list[float] = []
    for view in args.view:
        if len(view) < 2:
            print(f"vision-server sensor-check: view {view} needs a colour image and depth")
            return 2
        try:
            color = _read(view[0], cv2.IMREAD_COLOR)
            depth = [_read(p, cv2.IMREAD_UNCHANGED) for p in view[1:]]
            pose = qr_pose(
                color,
                depth,
                intrinsics.to_geometry(),
                expect=inspection.expect,
                side_m=inspection.side_m,
                corner_bias_px=inspection.corner_bias_px,
            )
        except (ValueError, AnalysisError) as exc:
            print(f"vision-server sensor-check: {view[0]}: skipped: {exc}")
            continue
        q = pose.quality
        ratios.append(q.depth_vs_side)
        gains.append([float(g) for g in q.shift_sensitivity])
        sides.append(q.side_px)
        grids.append(q.depth_vs_grid)
    try:
        reg = fit_depth_registration(
            ratios,
            gains,
            sides,
            corner_bias_px=inspection.corner_bias_px or 0.0,
            depth_vs_grid=grids,  # the module grid's, where found (issue 29)
        )
    except AnalysisError as exc:
        print(f"vision-server sensor-check: {exc}")
        return 2
    ok, verdict = registration_advice(reg)
    report = {
        "views": reg.views,
        "depth_scale": round(reg.scale, 5),
        "depth_scale_std": round(reg.scale_std, 5),
        "depth_shift_px": [round(x, 2) for x in reg.shift_px],
        "depth_shift_std_px": [round(x, 2) if np.isfinite(x) else None for x in reg.shift_std_px],
        "residual_rms": round(reg.residual_rms, 5),
        "ok": ok,
        "verdict": verdict,
    }
    if args.json is True:
        print(json.dumps(report))
    else:
        for key, value in report.items():
            print(f"{key:20} {value}")
    return 0 if ok else 1
