"""``robot-client``: talk to a vision server and run skills.

Commands: ``ping``, ``inspections``, ``inspect NAME [--image F] [--depth F ...]``, ``skills``,
``teach SKILL NAME [KEY=VALUE ...] [--from-current-pose]``, ``run SKILL NAME``,
``task run FILE``, ``taught list``, ``taught show NAME``, ``calibrate-intrinsics INSPECTION``;
``--json`` for machines.

The server: ``--server HOST:PORT``, ``--token-file PATH``, ``--tls``, ``--ca FILE`` (before or
after the command), else ``$CELLVISION_SERVER``, ``$CELLVISION_TOKEN`` or
``$CELLVISION_TOKEN_FILE``, ``$CELLVISION_TLS``, ``$CELLVISION_CA``; else 127.0.0.1:7878 in
plain TCP without a token.

Exit codes (both tools): 0 ok/pass, 1 fail verdict, 2 usage or configuration error,
3 connection error, 4 error answered by the server. With ``--json`` an error is printed on
stdout as ``{"error": {"kind": ..., "message": ..., "code": ...}}``.
"""

from __future__ import annotations

import argparse
import asyncio
import json
import os
import signal
import sys
from collections.abc import Awaitable, Callable, Sequence
from pathlib import Path
from typing import Any

import cv2
from rich.console import Console
from rich.markup import escape
from rich.table import Table
from rich.text import Text

from protocol import CellvisionError, ImagePayload, ImageRole, Result, array_from_payload
from protocol.cli import ErrorKind, ExitCode, Parser, ParserError, json_error, version_text
from protocol.image_files import (
    ImageFileError,
    check_overlay_path,
    encode_overlay,
    payload_from_file,
)
from protocol.result_view import result_json, result_view

from ..address import add_connection_options, endpoint_from_args, ssl_context
from ..client import ReconnectPolicy, VisionClient, overlay_image
from ..devices import DeviceError
from ..errors import ClientError
from .commission import add_commission_commands
from .hand_eye import add_hand_eye_command
from .sensor_check import add_sensor_check_command
from .skills import add_skill_commands

Command = Callable[[argparse.Namespace, VisionClient, Console], Awaitable[int]]

DESCRIPTION = """\
robot-client: talk to a vision server and run skills.

  robot-client ping | inspections
  robot-client inspect NAME [--image FILE] [--depth FILE ...] [--overlay out.png]
  robot-client skills | teach SKILL NAME [KEY=VALUE ...] | run SKILL NAME
  robot-client task run FILE | taught list | taught show NAME
  robot-client calibrate-intrinsics INSPECTION (--camera TOOL_CAMERA | --fixed)
               [--config SERVER.yaml [--yes]]
  robot-client calibrate-hand-eye INSPECTION --camera CAMERA [--config SERVER.yaml] [--yes]
  robot-client sensor-check QR_POSE_INSPECTION --camera RGBD_CAMERA [--start X Y Z R P Y]

The server: --server HOST:PORT, --token-file PATH, --tls, --ca FILE (before or after the
command), else $CELLVISION_SERVER, $CELLVISION_TOKEN or $CELLVISION_TOKEN_FILE,
$CELLVISION_TLS, $CELLVISION_CA; else 127.0.0.1:7878 in plain TCP without a token.

Exit codes (both tools): 0 ok/pass, 1 fail verdict, 2 usage or configuration error,
3 connection error, 4 error answered by the server. With --json everything on stdout is JSON,
errors as {"error": {"kind": ..., "message": ..., "code": ...}}. Output cut short by its
reader (| head) ends quietly with 141, as a Unix tool killed by SIGPIPE.
"""


async def _ping(args: argparse.Namespace, client: VisionClient, console: Console) -> int:
    welcome = client.welcome
    assert welcome is not None
    rtts = [await client.ping() for _ in range(args.count)]
    if args.json:
        print(
            json.dumps(
                {
                    "server": {"name": welcome.server_name, "version": welcome.server_version},
                    "protocol": list(welcome.version),
                    "rtt_ms": [round(r * 1000.0, 3) for r in rtts],
                }
            )
        )
    else:
        console.print(
            f"[green]PONG[/] from {welcome.server_name} {welcome.server_version} at "
            f"{client.host}:{client.port} (protocol {welcome.version[0]}.{welcome.version[1]}): "
            + ", ".join(f"{r * 1000.0:.2f} ms" for r in rtts)
        )
    return 0


async def _inspections(args: argparse.Namespace, client: VisionClient, console: Console) -> int:
    inspections = await client.list_inspections()
    if args.json:
        print(json.dumps({"inspections": list(inspections)}))
        return 0
    table = Table(title=f"Inspections on {client.host}:{client.port}")
    for column in ("name", "type", "camera", "source", "depth"):
        table.add_column(column)
    for item in inspections:
        table.add_row(
            str(item.get("name")),
            str(item.get("type", "")),
            str(item.get("camera", "")),
            str(item.get("camera_source", "")),
            "yes" if item.get("depth") else "no",
        )
    console.print(table)
    return 0


def _read_image(path: str, role: ImageRole) -> ImagePayload:
    """The payload for an image file of any format OpenCV reads (:mod:`protocol.image_files`);
    ValueError naming the file."""
    try:
        data = Path(path).read_bytes()
    except OSError as exc:
        raise ValueError(f"cannot read {path}: {exc.strerror or exc}") from None
    return payload_from_file(data, name=path, role=role)


def _prepare_inspect(args: argparse.Namespace) -> None:
    """Before connecting: read the images and check --overlay's folder and extension, so that
    a bad argument is a usage error and nothing is sent."""
    args.overlay_suffix = None
    if args.overlay:
        args.overlay_suffix = check_overlay_path(args.overlay, folder_exists=os.path.isdir)
    args.color_payload = _read_image(args.image, ImageRole.COLOR) if args.image else None
    args.depth_payloads = [_read_image(d, ImageRole.DEPTH) for d in args.depth]


async def _inspect(args: argparse.Namespace, client: VisionClient, console: Console) -> int:
    result = await client.inspect(
        args.name,
        args.color_payload,
        depth=args.depth_payloads,
        overlay=args.overlay_suffix is not None,
    )
    if args.json:
        print(json.dumps(result_json(result, image=args.image), default=str))
    else:
        title = Text(f"{args.image}: " if args.image else "")
        title.append_text(
            Text("PASS", style="bold green") if result.passed else Text("FAIL", style="bold red")
        )
        title.append(f" {result.inspection}" + (f" on {result.camera}" if result.camera else ""))
        timing = ", ".join(f"{k} {v:.1f} ms" for k, v in result.timing.items())
        title.append(f" ({timing})" if timing else "", style="dim")
        console.print(title, soft_wrap=True)  # a long path stays on its line, with its verdict
        _print_data(console, result.data)
    verdict = ExitCode.OK if result.passed else ExitCode.FAILED
    if args.overlay_suffix is not None:
        return max(verdict, _write_overlay(args, result))
    return verdict


def _print_data(console: Console, data: dict[str, Any]) -> None:
    """Fields, then one table per list (features, corners, ...), rounded as
    :mod:`protocol.result_view` says; every text goes in as Text, never as markup."""
    view = result_view(data)
    if view.fields:
        fields = Table(box=None, show_header=False, padding=(0, 1, 0, 2))
        fields.add_column(style="dim")
        fields.add_column()
        for name, value in view.fields:
            fields.add_row(Text(name), Text(value))
        console.print(fields)
    for table in view.tables:
        grid = Table(title=Text(table.title), title_justify="left", show_header=table.show_header)
        for column in table.columns:
            grid.add_column(Text(column), justify="right")
        for row in table.rows:
            grid.add_row(*(Text(cell) for cell in row))
        console.print(grid)


def _write_overlay(args: argparse.Namespace, result: Result) -> ExitCode:
    """Write the overlay (folder and extension were checked before connecting)."""
    picture = overlay_image(result)
    if picture is None:
        print(
            f"robot-client inspect: {result.inspection} drew no overlay; nothing written to "
            f"{args.overlay}",
            file=sys.stderr,
        )
        return ExitCode.OK
    try:
        Path(args.overlay).write_bytes(encode_overlay(picture, args.overlay_suffix))
    except (OSError, ImageFileError) as exc:
        message = exc.strerror if isinstance(exc, OSError) and exc.strerror else str(exc)
        return _report(
            ErrorKind.USAGE,
            f"--overlay {args.overlay}: cannot write: {message}",
            None,
            as_json=bool(args.json),
        )
    if not args.json:
        print(f"overlay written to {args.overlay}")
    return ExitCode.OK


def _prepare_capture(args: argparse.Namespace) -> None:
    """Before connecting: the output folder must exist (no folder is created unasked)."""
    if not os.path.isdir(args.out):
        raise ValueError(f"--out {args.out}: no such folder")
    if args.count < 1:
        raise ValueError(f"--count must be >= 1, got {args.count}")


async def _capture(args: argparse.Namespace, client: VisionClient, console: Console) -> int:
    """CAPTURE raw frames from a server camera and write each as a lossless PNG (depth as
    16-bit PNG in millimetres), for golden cases and offline tuning."""
    frames = await client.capture(args.camera, count=args.count, depth=args.depth)
    written: list[dict[str, Any]] = []
    frame = -1
    for payload in frames.images:
        if payload.role is ImageRole.COLOR:
            frame += 1
        suffix = "depth" if payload.role is ImageRole.DEPTH else "color"
        path = Path(args.out) / f"{args.camera}-{frame:03d}-{suffix}.png"
        array = array_from_payload(payload)
        try:
            path.write_bytes(encode_overlay(array, ".png"))
        except (OSError, ImageFileError) as exc:
            message = exc.strerror if isinstance(exc, OSError) and exc.strerror else str(exc)
            return _report(
                ErrorKind.USAGE, f"cannot write {path}: {message}", None, as_json=bool(args.json)
            )
        written.append({"file": str(path), "role": payload.role.value, "frame": frame})
    if args.json:
        print(json.dumps({"camera": frames.camera, "files": written}))
    else:
        for item in written:
            console.print(Text(f"wrote {item['file']}"))
    return ExitCode.OK


DEFAULT_TIMEOUT_S = 10.0


def _common(*, top: bool) -> Parser:
    """The options every command accepts, before or after its name."""
    parent = Parser(add_help=False)
    add_connection_options(parent, top=top)
    parent.add_argument(
        "--json",
        action="store_true",
        default=False if top else argparse.SUPPRESS,
        help="machine-readable output (errors too)",
    )
    return parent


def build_parser() -> argparse.ArgumentParser:
    parser = Parser(
        prog="robot-client",
        description=DESCRIPTION,
        formatter_class=argparse.RawDescriptionHelpFormatter,
        parents=[_common(top=True)],
    )
    parser.add_argument("--version", action="version", version=version_text("robot-client"))
    common = _common(top=False)
    sub = parser.add_subparsers(dest="command", required=True)
    ping = sub.add_parser("ping", parents=[common], help="check that the server answers")
    ping.add_argument("-n", "--count", type=int, default=1)
    ping.set_defaults(func=_ping)
    insp = sub.add_parser("inspections", parents=[common], help="list the server's inspections")
    insp.set_defaults(func=_inspections)
    one = sub.add_parser(
        "inspect", parents=[common], help="run an inspection (on an image file, else its camera)"
    )
    one.add_argument("name")
    one.add_argument(
        "--image",
        default=None,
        help="colour or gray image to send, 8-bit, any format OpenCV reads (PNG, JPEG, BMP, "
        "TIFF, WebP, PGM, ...)",
    )
    one.add_argument(
        "--depth",
        action="append",
        default=[],
        help="depth image, 16-bit gray in mm (PNG, TIFF, PGM, ...); repeat",
    )
    one.add_argument(
        "--overlay",
        default=None,
        metavar="PATH",
        help="save the overlay image here (.png, .jpg, ...; the folder must exist)",
    )
    one.set_defaults(func=_inspect, prepare=_prepare_inspect)
    grab = sub.add_parser(
        "capture",
        parents=[common],
        help="take raw frames from a server camera and save them as PNG files",
    )
    grab.add_argument("camera")
    grab.add_argument("-n", "--count", type=int, default=1, help="distinct frames to take")
    grab.add_argument("--depth", action="store_true", help="also the depth image of each frame")
    grab.add_argument(
        "--out", default=".", metavar="DIR", help="folder to write into (must exist; default .)"
    )
    grab.set_defaults(func=_capture, prepare=_prepare_capture)
    add_skill_commands(sub, common)
    add_commission_commands(sub, common)
    add_hand_eye_command(sub, common)
    add_sensor_check_command(sub, common)
    return parser


async def _run(args: argparse.Namespace, func: Command, console: Console) -> int:
    endpoint = endpoint_from_args(args)
    prepare = getattr(args, "prepare", None)
    if prepare is not None:  # read the command's files before connecting
        prepare(args)
    timeout_s = args.timeout if args.timeout is not None else DEFAULT_TIMEOUT_S
    client = VisionClient(
        endpoint.host,
        endpoint.port,
        auth_token=endpoint.token,
        ssl=ssl_context(endpoint),
        request_timeout_s=timeout_s,
        connect_timeout_s=timeout_s,
        # A busy server is asked again (after its retry-after hint) within the same timeout.
        busy_timeout_s=timeout_s,
        reconnect=ReconnectPolicy(attempts=0),
    )
    async with client:
        return await func(args, client, console)


def _classify(exc: BaseException) -> tuple[ErrorKind, str, str | None] | None:
    """(kind, message, wire code) of an error the command line reports; None: a bug."""
    if isinstance(exc, CellvisionError):
        return ErrorKind.SERVER, exc.message, exc.code.name
    if isinstance(exc, KeyError):
        return ErrorKind.USAGE, str(exc.args[0]) if exc.args else "not found", None
    if isinstance(exc, ValueError | LookupError):
        return ErrorKind.USAGE, str(exc), None
    if isinstance(exc, DeviceError):
        return ErrorKind.DEVICE, str(exc), None
    if isinstance(exc, ClientError):
        return ErrorKind.CONNECTION, str(exc), None
    return None


def _report(kind: ErrorKind, message: str, code: str | None, *, as_json: bool) -> ExitCode:
    if as_json:
        print(json.dumps(json_error(kind, message, code)))
    else:
        label = code or {ErrorKind.DEVICE: "device error"}.get(kind, "error")
        # One line, never wrapped: a path cut in two cannot be copied.
        Console(stderr=True).print(f"[red]{label}:[/] {escape(message)}", soft_wrap=True)
    return kind.exit_code


def _broken_pipe(console: Console) -> None:
    raise BrokenPipeError


def main(argv: Sequence[str] | None = None) -> int:
    # Rich ends a closed pipe with exit 1 (our "fail"): let it reach the one handler below.
    Console.on_broken_pipe = _broken_pipe  # type: ignore[method-assign,assignment]
    try:
        return _main(argv)
    except KeyboardInterrupt:
        # Ctrl-C: one line, not a traceback (a task says where it stopped before this).
        print("robot-client: interrupted", file=sys.stderr)
        return ExitCode.INTERRUPTED
    except BrokenPipeError:
        # The reader of stdout went away (`| head`): no traceback. stdout now points at
        # /dev/null so that Python's flush at exit does not fail again; the exit code is a
        # shell's for a command killed by SIGPIPE.
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, sys.stdout.fileno())
        os.close(devnull)
        return 128 + signal.SIGPIPE


def _main(argv: Sequence[str] | None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    try:
        args = build_parser().parse_args(argv)
    except ParserError as exc:
        if "--json" in argv:
            print(json.dumps(json_error(ErrorKind.USAGE, str(exc))))
        else:
            exc.parser.print_usage(sys.stderr)
            print(f"{exc.parser.prog}: error: {exc}", file=sys.stderr)
        return ExitCode.USAGE
    if "OPENCV_LOG_LEVEL" not in os.environ:
        # OpenCV's own [ WARN:...] lines: every failure they announce reaches the user as
        # our own error. $OPENCV_LOG_LEVEL set keeps them, for debugging.
        cv2.utils.logging.setLogLevel(cv2.utils.logging.LOG_LEVEL_SILENT)
    console = Console(stderr=False)
    try:
        if getattr(args, "sync", False):
            result: int = args.func(args, console)
            return result
        return asyncio.run(_run(args, args.func, console))
    except Exception as exc:
        classified = _classify(exc)
        if classified is None:
            raise
        return _report(*classified, as_json=bool(args.json))


if __name__ == "__main__":
    sys.exit(main())
