"""``vision-server``: serve, and (later) check configurations, run inspections offline and list
results."""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import logging
import signal
import sys
from collections.abc import Sequence

from protocol import DEFAULT_PORT

from .builtin import builtin_catalog
from .server import ServerSettings, VisionServer


def _serve(args: argparse.Namespace) -> int:
    settings = ServerSettings(host=args.host, port=args.port, auth_token=args.auth_token)
    catalog = builtin_catalog()

    async def main() -> int:
        server = VisionServer(catalog, settings)
        try:
            await server.start()
        except OSError as exc:  # port in use, address not on this machine, no permission
            print(
                f"vision-server: cannot listen on {settings.host}:{settings.port}: {exc}",
                file=sys.stderr,
            )
            return 1
        print(f"vision-server listening on {settings.host}:{server.port}", flush=True)
        loop = asyncio.get_running_loop()
        stop = asyncio.Event()
        for sig in (signal.SIGINT, signal.SIGTERM):
            with contextlib.suppress(NotImplementedError):
                loop.add_signal_handler(sig, stop.set)
        await stop.wait()
        await server.stop()
        return 0

    return asyncio.run(main())


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="vision-server", description=__doc__)
    parser.add_argument("-v", "--verbose", action="store_true", help="log each connection")
    sub = parser.add_subparsers(dest="command", required=True)
    serve = sub.add_parser("serve", help="serve inspections over TCP")
    serve.add_argument("--host", default="127.0.0.1", help="address to listen on")
    serve.add_argument("--port", type=int, default=DEFAULT_PORT, help="TCP port (0: any)")
    serve.add_argument("--auth-token", default=None, help="require this token in HELLO")
    serve.set_defaults(func=_serve)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    logging.basicConfig(
        level=logging.INFO if args.verbose else logging.WARNING,
        format="%(asctime)s %(name)s %(levelname)s %(message)s",
        stream=sys.stderr,
    )
    return int(args.func(args))


if __name__ == "__main__":
    sys.exit(main())
