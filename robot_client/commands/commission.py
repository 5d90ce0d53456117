"""``robot-client calibrate-intrinsics``: calibrate a camera's intrinsics from views of a board.

A camera on the tool (``--camera NAME``, a camera of the robot's devices): the robot starts
where the camera sees the board, moves through 15 planned poses over it and comes back. A fixed
server camera (``--fixed``): the operator shows the board, the command says which image
regions and tilts are still missing, and takes a view at each Enter. Either way the corners
come from the server's ``calibration_board`` inspection (the positional argument). Then the
solution is printed (intrinsics with standard deviations, RMS, per-view errors, coverage) and,
with ``--config FILE`` (the server's configuration), written as the camera's ``intrinsics``
after the user confirms (``--yes`` for scripts) and the server reloaded; a reload the server
refuses puts the previous file back, and one that leaves the server serving other intrinsics
(it runs another file) is an error (exit 2). The camera written is the one the images are of
(:func:`server_camera`). Views that leave image regions or board tilts uncovered
give intrinsics that cannot be trusted: they are reported, not written (unless
``--accept-incomplete``), and the command exits 1.
"""

from __future__ import annotations

import argparse
import asyncio
import datetime
import json
import sys
from pathlib import Path
from typing import Any

from rich.console import Console
from rich.markup import escape
from rich.table import Table

from protocol import CellvisionError, Reload, Reloaded
from protocol.cli import ExitCode

from ..address import endpoint_from_args, ssl_context
from ..client import ReconnectPolicy, VisionClient
from ..commissioning import IntrinsicsSolution, solve_intrinsics
from ..commissioning.collect import Collected, collect_fixed_views, collect_tool_views
from ..commissioning.config_file import file_hash, served_mismatch, write_intrinsics
from ..commissioning.coverage import Coverage
from ..devices import Devices
from .skills import _device_options, _devices

__all__ = ["add_commission_commands", "server_camera"]


def _inspection_camera(devices: Devices, inspection: str) -> tuple[str, str]:
    """The server camera of ``inspection``, which must be a ``calibration_board``, and where
    its images come from (SPEC §5.2 ``camera_source``: ``request`` or a server-side source)."""
    assert devices.vision is not None
    for item in devices.vision.list_inspections():
        if item.get("name") == inspection:
            if item.get("type") != "calibration_board":
                raise ValueError(
                    f"inspection {inspection!r} is a {item.get('type')}, not a calibration_board"
                )
            return str(item.get("camera")), str(item.get("camera_source", ""))
    raise ValueError(f"the server has no inspection named {inspection!r}")


def server_camera(devices: Devices, args: argparse.Namespace) -> str:
    """The server camera whose ``intrinsics`` in ``--config`` a commissioning command writes
    (``calibrate-intrinsics``) or reads (``calibrate-hand-eye``): the camera the images are of.

    One rule: ``--server-camera NAME`` is the user saying which it is; with ``--fixed`` the
    images are the inspection's own camera's; else they come from the robot's camera
    ``--camera ROBOT``, which is the server camera ``ROBOT`` or ``ROBOT`` without a
    ``_camera`` suffix (``tool_camera`` is ``tool``), and the inspection must run on that
    camera. Anything else would put one camera's intrinsics under another's name: a
    ``ValueError`` (exit 2) naming both, before the robot moves."""
    camera, source = _inspection_camera(devices, args.inspection)
    if args.server_camera:
        return str(args.server_camera)
    if getattr(args, "fixed", False) or not args.camera:
        return camera
    robot = str(args.camera)
    if camera in (robot, robot.removesuffix("_camera")):
        return camera
    own = f", which takes its own images ({source})" if source and source != "request" else ""
    raise ValueError(
        f"the images come from the robot's camera {robot!r} but inspection "
        f"{args.inspection!r} runs on the server camera {camera!r}{own}: {robot!r} is the "
        f"server camera {robot.removesuffix('_camera')!r} (the robot's camera NAME is the "
        f"server's NAME or NAME without '_camera'); use a calibration_board inspection on "
        f"that camera, or, if {robot!r} really is {camera!r}, say so with "
        f"--server-camera {camera}"
    )


def _ask_next(console: Console, interactive: bool) -> Any:
    def next_view(index: int, coverage: Coverage | None) -> bool:
        if coverage is not None:
            console.print(escape(f"  {coverage.describe()}"), soft_wrap=True)
        if not interactive:
            return True
        answer = console.input(
            f"view {index + 1}: show the board, then Enter (q: solve with the views so far) "
        )
        return answer.strip().lower() != "q"

    return next_view


def _solution_json(solution: IntrinsicsSolution, collected: Collected) -> dict[str, Any]:
    k = solution.intrinsics
    return {
        "intrinsics": {
            "width": k.width,
            "height": k.height,
            "fx": k.fx,
            "fy": k.fy,
            "cx": k.cx,
            "cy": k.cy,
            "distortion": list(k.dist),
        },
        "std": solution.std,
        "rms_px": solution.rms_px,
        "board": collected.board,
        "views": [
            {
                "label": v.label,
                "corners": v.corners,
                "rms_px": v.rms_px,
                "used": v.used,
                "reason": v.reason,
            }
            for v in solution.views
        ],
        "skipped": [{"label": label, "reason": reason} for label, reason in collected.skipped],
        "coverage": {
            "corners": [list(row) for row in solution.coverage.corners],
            "tilts": solution.coverage.tilts,
            "missing_regions": list(solution.coverage.missing_regions),
            "missing_tilts": list(solution.coverage.missing_tilts),
        },
    }


def _print_solution(console: Console, solution: IntrinsicsSolution, collected: Collected) -> None:
    k, std = solution.intrinsics, solution.std
    console.print(
        f"[bold]intrinsics[/] of {k.width}x{k.height} images from {solution.used} of "
        f"{len(solution.views)} views ({escape(collected.board)}):"
    )
    table = Table("parameter", "value", "std dev")
    for name in ("fx", "fy", "cx", "cy"):
        table.add_row(name, f"{getattr(k, name):.3f} px", f"{std[name]:.3f} px")
    for name, value in zip(("k1", "k2", "p1", "p2", "k3"), k.dist, strict=True):
        table.add_row(name, f"{value:.6f}", f"{std[name]:.6f}")
    console.print(table)
    console.print(f"RMS reprojection error: [bold]{solution.rms_px:.3f} px[/]")
    views = Table("view", "corners", "RMS px", "used")
    for v in solution.views:
        views.add_row(v.label, str(v.corners), f"{v.rms_px:.3f}", "yes" if v.used else v.reason)
    console.print(views)
    for label, reason in collected.skipped:
        console.print(escape(f"not taken: {label}: {reason}"), soft_wrap=True)
    console.print(escape(f"coverage: {solution.coverage.describe()}"), soft_wrap=True)


async def _reload(args: argparse.Namespace) -> Reloaded:
    endpoint = endpoint_from_args(args)
    timeout_s = args.timeout if args.timeout is not None else 10.0
    client = VisionClient(
        endpoint.host,
        endpoint.port,
        auth_token=endpoint.token,
        ssl=ssl_context(endpoint),
        request_timeout_s=timeout_s,
        connect_timeout_s=timeout_s,
        reconnect=ReconnectPolicy(attempts=0),
    )
    async with client:
        answer = await client.request(Reload)
    assert isinstance(answer, Reloaded)
    return answer


def _write(
    args: argparse.Namespace,
    console: Console,
    solution: IntrinsicsSolution,
    collected: Collected,
    camera: str,
) -> dict[str, Any]:
    """Write and reload after the user confirms; what was done, for --json."""
    path = Path(args.config)
    if not args.yes:
        if args.json or not sys.stdin.isatty():
            if not args.json:
                console.print("not written: confirm with --yes (no terminal to ask at)")
            return {"written": False, "reason": "not confirmed (--yes)"}
        answer = console.input(
            f"write these intrinsics for camera {escape(camera)!r} into {escape(str(path))} "
            "and reload the server? \\[y/N] "
        )
        if answer.strip().lower() not in ("y", "yes"):
            console.print("not written")
            return {"written": False, "reason": "declined"}
    today = datetime.datetime.now(datetime.UTC).strftime("%Y-%m-%d %H:%M UTC")
    note = (
        f"{today} by robot-client calibrate-intrinsics: {collected.board}, "
        f"{solution.used} views, RMS {solution.rms_px:.3f} px"
    )
    backup = write_intrinsics(path, camera, solution.intrinsics, note)
    try:
        reloaded = asyncio.run(_reload(args))
    except CellvisionError:
        backup.replace(path)  # the server keeps its configuration; so does the file
        if not args.json:
            Console(stderr=True).print(
                escape(f"the server refused the new file: {path} is put back as it was"),
                soft_wrap=True,
            )
        raise
    # A reload re-reads the file the server was started with, which need not be --config:
    # only the intrinsics it now serves say whether it took the new ones.
    mismatch = served_mismatch(reloaded.cameras, camera, solution.intrinsics)
    if mismatch is not None:
        raise ValueError(
            f"wrote the intrinsics of camera {camera!r} into {path} (config hash "
            f"{file_hash(path)}; previous file: {backup}), but the server reloaded another "
            f"configuration (config hash {reloaded.config_hash}): {mismatch}. The server "
            f"re-reads the file it was started with: give that file to --config, or restart "
            f"the server with {path} (vision-server serve --config {path})"
        )
    written_hash = file_hash(path)
    if written_hash == reloaded.config_hash:
        served = f"the server reloaded it and serves them (config hash {reloaded.config_hash})"
    else:
        # The same intrinsics, from another file (e.g. a second pass over a copy): true today,
        # but later edits of --config will not reach the server.
        served = (
            f"the server serves them, but from another file (its config hash "
            f"{reloaded.config_hash} is not {path}'s {written_hash}): later edits of {path} "
            "will not reach it"
        )
    if not args.json:
        console.print(
            escape(
                f"wrote the intrinsics of camera {camera!r} into {path} (previous file: "
                f"{backup}); {served}"
            ),
            soft_wrap=True,
        )
    return {
        "written": True,
        "config": str(path),
        "config_hash": reloaded.config_hash,
        "file_hash": written_hash,
    }


def cmd_calibrate_intrinsics(args: argparse.Namespace, console: Console) -> int:
    if args.views < 4:
        raise ValueError(f"--views must be >= 4, got {args.views}")
    devices = _devices(args)
    try:
        camera = server_camera(devices, args) if args.config else ""
        if args.fixed:
            interactive = not args.yes and not args.json and sys.stdin.isatty()
            collected = collect_fixed_views(
                devices,
                inspection=args.inspection,
                count=args.views,
                next_view=_ask_next(console, interactive) if not args.json else lambda i, c: True,
                focal_px=args.focal_px,
            )
        else:
            if not args.camera:
                raise ValueError("give --camera NAME (a camera on the tool) or --fixed")
            collected = collect_tool_views(
                devices,
                camera=args.camera,
                inspection=args.inspection,
                tilt_deg=args.tilt_deg,
                progress=None
                if args.json
                else lambda message, _: console.print(escape(f"  {message}")),
            )
    finally:
        devices.close()
    if collected.image_size is None:
        raise ValueError("the board was found in no view")
    solution = solve_intrinsics(collected.views, collected.image_size)
    out = _solution_json(solution, collected)
    if not args.json:
        _print_solution(console, solution, collected)
    coverage = solution.coverage
    if not coverage.complete:
        # Views that miss image regions or tilts leave parameters undetermined: the RMS can be
        # small and the standard deviations too while fx is off by a third.
        missing = ", ".join((*coverage.missing_regions, *coverage.missing_tilts))
        if not args.json:
            console.print(
                f"[red]coverage incomplete[/] (missing: {escape(missing)}): these intrinsics "
                "are not to be trusted; show the board there and calibrate again",
                soft_wrap=True,
            )
    if args.config and (coverage.complete or args.accept_incomplete):
        out["config"] = _write(args, console, solution, collected, camera)
    elif args.config:
        out["config"] = {"written": False, "reason": "coverage incomplete"}
        if not args.json:
            console.print("not written (--accept-incomplete writes it all the same)")
    if args.json:
        print(json.dumps(out))
    return int(ExitCode.OK if coverage.complete else ExitCode.FAILED)


def add_commission_commands(sub: Any, common: argparse.ArgumentParser) -> None:
    """Add ``calibrate-intrinsics`` to the ``robot-client`` subparsers."""
    cal = sub.add_parser(
        "calibrate-intrinsics",
        parents=[common, _device_options()],
        help="calibrate a camera's intrinsics from views of a calibration board",
    )
    cal.add_argument("inspection", help="the server's calibration_board inspection")
    cal.add_argument("--camera", default=None, help="the robot's tool camera to move around")
    cal.add_argument(
        "--fixed",
        action="store_true",
        help="the inspection's own (fixed) server camera; the operator shows the board",
    )
    cal.add_argument("--views", type=int, default=15, help="views to take with --fixed")
    cal.add_argument("--tilt-deg", type=float, default=30.0, help="tilt of the tilted views")
    cal.add_argument(
        "--focal-px", type=float, default=None, help="--fixed: a focal length guess (px)"
    )
    cal.add_argument(
        "--config", default=None, metavar="FILE", help="the server's configuration to write into"
    )
    cal.add_argument(
        "--server-camera",
        default=None,
        help="the server camera in --config the images are of, to write (default: the "
        "inspection's camera, which must be --camera's: NAME or NAME without '_camera')",
    )
    cal.add_argument("--yes", action="store_true", help="write without asking")
    cal.add_argument(
        "--accept-incomplete",
        action="store_true",
        help="write even when image regions or board tilts are missing from the views",
    )
    cal.set_defaults(func=cmd_calibrate_intrinsics, sync=True)
