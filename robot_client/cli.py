"""``robot-client``: talk to a vision server and run skills.

Commands: ``ping``, ``inspections``, ``inspect NAME [--image F] [--depth F ...]``, ``skills``,
``teach SKILL NAME [KEY=VALUE ...] [--from-current-pose]``, ``run SKILL NAME``,
``task run FILE``, ``taught list``, ``taught show NAME``; ``--json`` for machines.

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
import sys
from collections.abc import Awaitable, Callable, Sequence
from typing import Any

import cv2
import numpy.typing as npt
from rich.console import Console
from rich.markup import escape
from rich.table import Table

from protocol import CellvisionError
from protocol.cli import ErrorKind, ExitCode, Parser, ParserError, json_error

from .address import add_connection_options, endpoint_from_args, ssl_context
from .cli_skills import add_skill_commands
from .client import ReconnectPolicy, VisionClient, overlay_image
from .devices import DeviceError
from .errors import ClientError

Command = Callable[[argparse.Namespace, VisionClient, Console], Awaitable[int]]


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


def _read_image(path: str, what: str) -> npt.NDArray[Any]:
    image = cv2.imread(path, cv2.IMREAD_UNCHANGED)
    if image is None:
        raise ValueError(f"{what} {path!r}: cannot read the image")
    result: npt.NDArray[Any] = image
    return result


async def _inspect(args: argparse.Namespace, client: VisionClient, console: Console) -> int:
    image = _read_image(args.image, "--image") if args.image else None
    depth = [_read_image(d, "--depth") for d in args.depth]
    result = await client.inspect(args.name, image, depth=depth, overlay=bool(args.overlay))
    if args.overlay:
        picture = overlay_image(result)
        if picture is not None:
            cv2.imwrite(args.overlay, picture)
    if args.json:
        print(
            json.dumps(
                {
                    "inspection": result.inspection,
                    "verdict": "pass" if result.passed else "fail",
                    "camera": result.camera,
                    "data": result.data,
                    "timing": result.timing,
                },
                default=str,
            )
        )
    else:
        verdict = "[green]PASS[/]" if result.passed else "[red]FAIL[/]"
        console.print(
            f"{verdict} {result.inspection}" + (f" on {result.camera}" if result.camera else "")
        )
        for key, value in result.data.items():
            console.print(f"  {key}: {value}")
        console.print("  timing: " + ", ".join(f"{k} {v:.2f} ms" for k, v in result.timing.items()))
    return ExitCode.OK if result.passed else ExitCode.FAILED


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
    parser = Parser(prog="robot-client", description=__doc__, parents=[_common(top=True)])
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
    one.add_argument("--image", default=None, help="colour image file to send")
    one.add_argument("--depth", action="append", default=[], help="depth PNG (uint16 mm); repeat")
    one.add_argument("--overlay", default=None, metavar="PNG", help="save the overlay image here")
    one.set_defaults(func=_inspect)
    add_skill_commands(sub, common)
    return parser


async def _run(args: argparse.Namespace, func: Command, console: Console) -> int:
    endpoint = endpoint_from_args(args)
    timeout_s = args.timeout if args.timeout is not None else DEFAULT_TIMEOUT_S
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


def _report(kind: ErrorKind, message: str, code: str | None, *, as_json: bool) -> int:
    if as_json:
        print(json.dumps(json_error(kind, message, code)))
    else:
        label = code or {ErrorKind.DEVICE: "device error"}.get(kind, "error")
        Console(stderr=True).print(f"[red]{label}:[/] {escape(message)}")
    return kind.exit_code


def main(argv: Sequence[str] | None = None) -> int:
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
