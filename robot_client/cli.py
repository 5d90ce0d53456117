"""``robot-client``: talk to a vision server and run skills.

Commands: ``ping``, ``inspections``, ``inspect NAME [--image F] [--depth F ...]``, ``skills``,
``teach SKILL NAME [KEY=VALUE ...] [--from-current-pose]``, ``run SKILL NAME``,
``task run FILE``, ``taught list``, ``taught show NAME``; ``--json`` for machines.

The server address comes from ``--server HOST:PORT``, else ``$CELLVISION_SERVER``, else
127.0.0.1 on the default port 7878.
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

from .address import resolve_server
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
                    "passed": result.passed,
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
    return 0 if result.passed else 1


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="robot-client", description=__doc__)
    parser.add_argument("--server", help="HOST:PORT of the vision server")
    parser.add_argument("--auth-token", default=None, help="token for the server's HELLO")
    parser.add_argument("--timeout", type=float, default=10.0, help="seconds per request")
    sub = parser.add_subparsers(dest="command", required=True)
    ping = sub.add_parser("ping", help="check that the server answers")
    ping.add_argument("-n", "--count", type=int, default=1)
    ping.add_argument("--json", action="store_true")
    ping.set_defaults(func=_ping)
    insp = sub.add_parser("inspections", help="list the server's inspections")
    insp.add_argument("--json", action="store_true")
    insp.set_defaults(func=_inspections)
    one = sub.add_parser("inspect", help="run an inspection (on an image file, else its camera)")
    one.add_argument("name")
    one.add_argument("--image", default=None, help="colour image file to send")
    one.add_argument("--depth", action="append", default=[], help="depth PNG (uint16 mm); repeat")
    one.add_argument("--overlay", default=None, metavar="PNG", help="save the overlay image here")
    one.add_argument("--json", action="store_true")
    one.set_defaults(func=_inspect)
    add_skill_commands(sub)
    return parser


async def _run(args: argparse.Namespace, func: Command, console: Console) -> int:
    host, port = resolve_server(args.server)
    client = VisionClient(
        host,
        port,
        auth_token=args.auth_token,
        request_timeout_s=args.timeout,
        connect_timeout_s=args.timeout,
        reconnect=ReconnectPolicy(attempts=0),
    )
    async with client:
        return await func(args, client, console)


def main(argv: Sequence[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    console = Console(stderr=False)
    err = Console(stderr=True)
    try:
        if getattr(args, "sync", False):
            result: int = args.func(args, console)
            return result
        return asyncio.run(_run(args, args.func, console))
    except (ValueError, LookupError) as exc:
        err.print(
            f"[red]error:[/] {escape(str(exc.args[0] if isinstance(exc, KeyError) else exc))}"
        )
        return 2
    except DeviceError as exc:
        err.print(f"[red]device error:[/] {escape(str(exc))}")
        return 1
    except CellvisionError as exc:
        err.print(f"[red]{exc.code.name}:[/] {escape(exc.message)}")
        return 1
    except ClientError as exc:
        err.print(f"[red]error:[/] {escape(str(exc))}")
        return 1


if __name__ == "__main__":
    sys.exit(main())
