"""``vision-server``: serve inspections, check a configuration, run an inspection offline on
image files, list logged results, and check or reload a running server.

    vision-server serve --config cell.yaml          # SIGHUP or `vision-server reload` re-reads it
    vision-server check-config cell.yaml
    vision-server run --config cell.yaml cap_locate --image cap.png [--json] [--overlay out.png]
    vision-server test-inspections [PATH ...] [--json] [--update]   # golden cases
    vision-server results --config cell.yaml --since 1h [--inspection NAME] [--json]
    vision-server ping --server 127.0.0.1:7878
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import json
import logging
import os
import signal
import sys
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import cv2
from rich.console import Console
from rich.table import Table

from protocol import (
    DEFAULT_PORT,
    CellvisionError,
    ImageEncoding,
    ImagePayload,
    ImageRole,
    Inspect,
    Ping,
    Reload,
    Reloaded,
    array_from_payload,
)

from . import decoder_limits
from .admin import AdminError, call
from .builtin import builtin_catalog
from .cameras import RequestCamera, RequestCameraSettings
from .catalog import Catalog, Inspection
from .config import CellConfig, ConfigError, load_config
from .results_cli import results_command
from .server import ServerSettings, VisionServer

log = logging.getLogger("vision_server")
CONFIG_ENV = "CELLVISION_CONFIG"


def _address(text: str | None) -> tuple[str, int]:
    if not text:
        return "127.0.0.1", DEFAULT_PORT
    host, sep, port = text.rpartition(":")
    if not sep:
        return text, DEFAULT_PORT
    return host.strip("[]") or "127.0.0.1", int(port)


# ----------------------------------------------------------------------------- serve


def _serve(args: argparse.Namespace) -> int:
    config_path = args.config or os.environ.get(CONFIG_ENV)
    runtime = None
    if config_path:
        from .runtime import CellRuntime

        try:
            # OpenCV fixes its image-size limits when it loads: settle them (perhaps by
            # re-executing) before the runtime opens cameras and the result log.
            limit = load_config(config_path).server.max_image_pixels
            decoder_limits.ensure(limit, argv=args.reexec_argv)
            runtime = CellRuntime(config_path)
        except ConfigError as exc:
            print(f"vision-server: invalid configuration: {exc}", file=sys.stderr)
            return 2
        base = runtime.config.server
        catalog = runtime.catalog
    else:
        base = ServerSettings()
        catalog = builtin_catalog()
    overrides: dict[str, Any] = {}
    if args.host is not None:
        overrides["host"] = args.host
    if args.port is not None:
        overrides["port"] = args.port
    if args.auth_token is not None:
        overrides["auth_token"] = args.auth_token
    settings = ServerSettings(**{**base.__dict__, **overrides})
    decoder_limits.ensure(settings.max_image_pixels, argv=args.reexec_argv)

    def reload() -> Catalog:
        assert runtime is not None
        return runtime.reload()

    async def main() -> int:
        server = VisionServer(
            catalog,
            settings,
            results=None if runtime is None else runtime.results,
            reloader=None if runtime is None else reload,
        )
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

        def on_hup() -> None:
            try:
                server.reload()
                print(
                    f"vision-server: configuration reloaded ({server.catalog.config_hash})",
                    flush=True,
                )
            except (ConfigError, CellvisionError) as exc:
                log.error("reload refused, the old configuration stays: %s", exc)
                print(
                    f"vision-server: reload refused, old configuration kept: {exc}",
                    file=sys.stderr,
                    flush=True,
                )

        if runtime is not None:
            with contextlib.suppress(NotImplementedError):
                loop.add_signal_handler(signal.SIGHUP, on_hup)
        await stop.wait()
        await server.stop()
        return 0

    try:
        return asyncio.run(main())
    finally:
        if runtime is not None:
            runtime.close()


# ----------------------------------------------------------------------------- check-config


def _check_config(args: argparse.Namespace) -> int:
    console = Console()
    try:
        config = load_config(args.file)
    except ConfigError as exc:
        if args.json:
            print(
                json.dumps({"valid": False, "error": str(exc), "line": exc.line, "path": exc.path})
            )
        else:
            Console(stderr=True).print(f"[red]invalid:[/] {exc}", highlight=False)
        return 1
    if args.json:
        print(json.dumps(_summary(config)))
        return 0
    table = Table(title=f"{args.file}: valid (config hash {config.config_hash})")
    for column in ("inspection", "type", "camera", "source", "roi"):
        table.add_column(column)
    for inspection in config.inspections:
        settings = config.cameras[inspection.camera]
        source = next(k for k, v in _sources().items() if isinstance(settings, v))
        roi = getattr(getattr(inspection, "common", None), "roi", None)
        table.add_row(
            inspection.name,
            inspection.type,
            inspection.camera,
            source,
            "whole image" if roi is None else str(list(roi)),
        )
    console.print(table)
    return 0


def _sources() -> dict[str, type]:
    from .cameras import SOURCE_NAMES

    return dict(SOURCE_NAMES)


def _summary(config: CellConfig) -> dict[str, Any]:
    return {
        "valid": True,
        "config_hash": config.config_hash,
        "server": {"host": config.server.host, "port": config.server.port},
        "cameras": {
            name: next(k for k, v in _sources().items() if isinstance(s, v))
            for name, s in config.cameras.items()
        },
        "inspections": [
            {"name": i.name, "type": i.type, "camera": i.camera} for i in config.inspections
        ],
    }


# ----------------------------------------------------------------------------- run


def _run(args: argparse.Namespace) -> int:
    """One inspection on image files, through the server's own request path."""
    err = Console(stderr=True)
    try:
        config = load_config(args.config)
    except ConfigError as exc:
        err.print(f"[red]invalid configuration:[/] {exc}", highlight=False)
        return 2
    inspection = next((i for i in config.inspections if i.name == args.inspection), None)
    if inspection is None:
        err.print(
            f"[red]no inspection named {args.inspection!r}[/]; configured: "
            f"{', '.join(i.name for i in config.inspections)}"
        )
        return 2
    server = offline_server(
        inspection,
        config.cameras[inspection.camera],
        config.base_dir,
        config_hash=config.config_hash,
    )
    try:
        images = [image_payload(Path(args.image), ImageRole.COLOR)]
        images += [image_payload(Path(p), ImageRole.DEPTH) for p in args.depth]
    except ValueError as exc:
        err.print(f"[red]error:[/] {exc}")
        return 2
    request = Inspect(1, inspection.name, tuple(images), overlay=args.overlay is not None)

    async def once() -> Any:
        return await server.run_inspection(request, peer="offline")

    try:
        result = asyncio.run(once())
    except CellvisionError as exc:
        if args.json:
            print(json.dumps({"error": exc.code.name, "message": exc.message}))
        else:
            err.print(f"[red]{exc.code.name}:[/] {exc.message}", highlight=False)
        return 1
    if args.overlay is not None and result.images:
        overlay = array_from_payload(result.images[0])
        cv2.imwrite(str(args.overlay), overlay)
    if args.json:
        print(
            json.dumps(
                {
                    "inspection": result.inspection,
                    "verdict": "pass" if result.passed else "fail",
                    "data": result.data,
                    "timing": result.timing,
                }
            )
        )
    else:
        console = Console()
        verdict = "[green]PASS[/]" if result.passed else "[red]FAIL[/]"
        console.print(f"{result.inspection}: {verdict} ({result.timing['compute_ms']:.1f} ms)")
        console.print_json(json.dumps(result.data))
        if args.overlay is not None:
            console.print(f"overlay written to {args.overlay}")
    return 0 if result.passed else 3


def offline_server(
    inspection: Inspection, settings: Any, base_dir: Path, *, config_hash: str = ""
) -> VisionServer:
    """A VisionServer that does not listen, serving ``inspection`` offline: its camera is
    replaced by one whose images come with the request, with the same intrinsics; everything
    after that (``run_inspection``) is the serving code path. Used by ``run`` and
    ``test-inspections``."""
    camera = RequestCamera(
        inspection.camera,
        RequestCameraSettings(getattr(settings, "intrinsics", None), depth=inspection.uses_depth),
    )
    if camera.intrinsics is None and inspection.uses_depth:
        camera = _with_scene_intrinsics(inspection.camera, settings, base_dir) or camera
    catalog = Catalog.build([camera], [inspection], config_hash=config_hash)
    return VisionServer(catalog, ServerSettings(workers=1))


def _with_scene_intrinsics(name: str, settings: Any, base_dir: Path) -> RequestCamera | None:
    """For a sim camera without configured intrinsics, the scene camera's own."""
    from .cameras import SimCameraSettings, make_camera

    if not isinstance(settings, SimCameraSettings):
        return None
    sim = make_camera(name, settings, base_dir=base_dir)
    try:
        return RequestCamera(name, RequestCameraSettings(sim.intrinsics, depth=True))
    finally:
        sim.close()


def image_payload(path: Path, role: ImageRole) -> ImagePayload:
    try:
        data = path.read_bytes()
    except OSError as exc:
        raise ValueError(f"cannot read {path}: {exc}") from None
    suffix = path.suffix.lower()
    if suffix == ".png":
        return ImagePayload(ImageEncoding.PNG, 0, 0, data, role)
    if suffix in (".jpg", ".jpeg"):
        return ImagePayload(ImageEncoding.JPEG, 0, 0, data, role)
    raise ValueError(f"{path}: only .png and .jpg/.jpeg images are read")


# ----------------------------------------------------------------------------- test-inspections


def _test_inspections(args: argparse.Namespace) -> int:
    """Golden cases (inspection + images + expected results) through the serving code path."""
    from .golden import golden_command

    return golden_command(args.paths, json_out=args.json, update=args.update)


# ----------------------------------------------------------------------------- results, admin


def _results(args: argparse.Namespace) -> int:
    db = args.db
    if db is None:
        config_path = args.config or os.environ.get(CONFIG_ENV)
        if not config_path:
            Console(stderr=True).print("[red]error:[/] give --db PATH or --config FILE")
            return 2
        try:
            config = load_config(config_path)
        except ConfigError as exc:
            Console(stderr=True).print(f"[red]invalid configuration:[/] {exc}", highlight=False)
            return 2
        if config.results.path is None:
            Console(stderr=True).print("[red]error:[/] the result log is disabled in the config")
            return 1
        db = config.results.path
    return results_command(
        Path(db),
        since=args.since,
        inspection=args.inspection,
        json_out=args.json,
        limit=args.limit,
        failed_only=args.failed,
        console=Console(),
    )


def _ping(args: argparse.Namespace) -> int:
    host, port = _address(args.server)
    try:
        call(
            host,
            port,
            lambda rid: Ping(rid, "health"),
            auth_token=args.auth_token,
            timeout_s=args.timeout,
        )
    except (AdminError, CellvisionError) as exc:
        print(f"vision-server ping: {host}:{port}: {exc}", file=sys.stderr)
        return 1
    print(f"{host}:{port} answers")
    return 0


def _reload(args: argparse.Namespace) -> int:
    host, port = _address(args.server)
    try:
        answer = call(host, port, Reload, auth_token=args.auth_token, timeout_s=args.timeout)
    except (AdminError, CellvisionError) as exc:
        print(f"vision-server reload: {host}:{port}: {exc}", file=sys.stderr)
        return 1
    assert isinstance(answer, Reloaded)
    names = ", ".join(str(i.get("name")) for i in answer.inspections)
    print(f"{host}:{port} reloaded: config hash {answer.config_hash}; inspections: {names}")
    return 0


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="vision-server", description=__doc__, formatter_class=argparse.RawTextHelpFormatter
    )
    parser.add_argument("-v", "--verbose", action="store_true", help="log each connection")
    sub = parser.add_subparsers(dest="command", required=True)

    serve = sub.add_parser("serve", help="serve inspections over TCP")
    serve.add_argument(
        "--config",
        help=f"cell configuration (default: ${CONFIG_ENV}; "
        "without one, a built-in demo inspection)",
    )
    serve.add_argument("--host", default=None, help="address to listen on (default 127.0.0.1)")
    serve.add_argument("--port", type=int, default=None, help="TCP port (0: any)")
    serve.add_argument("--auth-token", default=None, help="require this token in HELLO")
    serve.set_defaults(func=_serve)

    check = sub.add_parser("check-config", help="validate a configuration file")
    check.add_argument("file")
    check.add_argument("--json", action="store_true")
    check.set_defaults(func=_check_config)

    run = sub.add_parser("run", help="run one inspection offline on image files")
    run.add_argument("--config", required=True)
    run.add_argument("inspection")
    run.add_argument("--image", required=True, help="colour image (PNG or JPEG)")
    run.add_argument("--depth", action="append", default=[], help="depth PNG (uint16 mm)")
    run.add_argument("--json", action="store_true")
    run.add_argument("--overlay", type=Path, help="write the overlay image here (PNG)")
    run.set_defaults(func=_run)

    golden = sub.add_parser(
        "test-inspections", help="check inspections against known images (golden cases)"
    )
    golden.add_argument(
        "paths", nargs="*", help="case folders or folders of cases (default: test_inspections)"
    )
    golden.add_argument("--json", action="store_true", help="one JSON report")
    golden.add_argument(
        "--update",
        action="store_true",
        help="rewrite expected.yaml from the results, show the diff",
    )
    golden.set_defaults(func=_test_inspections)

    results = sub.add_parser("results", help="list logged inspection results")
    results.add_argument("--config", help="find the log through the configuration")
    results.add_argument("--db", type=Path, help="the result log (SQLite file)")
    results.add_argument("--since", help="e.g. 10m, 2h, 1d or an ISO date/time")
    results.add_argument("--inspection")
    results.add_argument("--failed", action="store_true", help="only failed inspections")
    results.add_argument("--limit", type=int, default=100)
    results.add_argument("--json", action="store_true", help="JSON lines")
    results.set_defaults(func=_results)

    ping = sub.add_parser("ping", help="check that a server answers (the container health check)")
    ping.add_argument("--server", help="HOST:PORT (default 127.0.0.1:7878)")
    ping.add_argument("--auth-token")
    ping.add_argument("--timeout", type=float, default=3.0)
    ping.set_defaults(func=_ping)

    reload = sub.add_parser("reload", help="ask a running server to re-read its configuration")
    reload.add_argument("--server", help="HOST:PORT (default 127.0.0.1:7878)")
    reload.add_argument("--auth-token")
    reload.add_argument("--timeout", type=float, default=10.0)
    reload.set_defaults(func=_reload)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    # Run as a program (not called from Python), serve may re-execute itself: decoder_limits.
    args.reexec_argv = list(sys.orig_argv) if argv is None else None
    logging.basicConfig(
        level=logging.INFO if args.verbose else logging.WARNING,
        format="%(asctime)s %(name)s %(levelname)s %(message)s",
        stream=sys.stderr,
    )
    return int(args.func(args))


if __name__ == "__main__":
    sys.exit(main())
