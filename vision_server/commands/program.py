"""vision-server: serve inspections, check a configuration, run an inspection offline on
image files, list logged results, check a depth camera against a QR board, print a PLC's
register map, and check or reload a running server.

    vision-server serve --config cell.yaml          # SIGHUP or "vision-server reload" re-reads it
                      [--host ADDR] [--port N]      # the binary protocol (server.host, .port)
                      [--console-port N | --no-console] [--line-port N | --no-line]
                      [--modbus-port N | --no-modbus]   # the front-ends the file enables
                      [--opcua-port N | --no-opcua]
    vision-server check-config cell.yaml
    vision-server run --config cell.yaml cap_locate --image cap.png [--image more.bmp ...]
                      [--json] [--overlay out.png]
    vision-server run --config cell.yaml station_pose --recording DIR [--frame N ...]
    vision-server test-inspections [PATH ...] [--json] [--update]   # golden cases
    vision-server test-inspections --config cell.yaml --from-recording DIR --inspection NAME
                      --out CASE [--frame N ...]   # a golden case from a recording
    vision-server results --config cell.yaml --since 1h [--inspection NAME] [--json]
    vision-server replay NAME --config changed.yaml [--last N] [--json]   # verdicts it flips
    vision-server train NAME --config cell.yaml --images 'good/*.png' [--step S] [--reload]
                      # an anomaly inspection's model from good images
    vision-server record CAMERA --config cell.yaml --out DIR [--frames N] [--max-bytes SIZE]
                      [--duration S] [--interval S] [--format auto|cellvision|realsense]
    vision-server modbus-map cell.yaml [--json]   # the PLC's register map (protocol/MODBUS.md)
    vision-server history --config cell.yaml [list | show V | diff V]   # the file's versions
    vision-server sensor-check --config cell.yaml station_pose --view c1.png d1.png ...
                      [--json]   # a depth camera's misregistration and scale (guide 7.3)
    vision-server ping [--server HOST:PORT] [--token-file PATH] [--tls] [--ca FILE]
    vision-server reload [...the same options]

Reaching a server (ping, reload): the command line, else $CELLVISION_SERVER, $CELLVISION_TOKEN
or $CELLVISION_TOKEN_FILE, $CELLVISION_TLS, $CELLVISION_CA, else the server section of --config
or $CELLVISION_CONFIG (its port, token and certificate), else 127.0.0.1:7878. Options may come
before or after the command.

Exit codes (both tools): 0 ok/pass, 1 fail verdict, 2 usage or configuration error (an
invalid file for check-config too),
3 connection error (or serve cannot listen), 4 error answered by the server (or, offline, by the
inspection). With --json an error is printed on stdout as {"error": {"kind", "message", "code"}}.
Output cut short by its reader (| head) ends quietly with 141, as a Unix tool killed by SIGPIPE.
"""

from __future__ import annotations

import argparse
import asyncio
import dataclasses
import json
import logging
import os
import signal
import sys
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
from rich.console import Console
from rich.table import Table
from rich.text import Text

from protocol import (
    CellvisionError,
    ImageRole,
    Message,
    Ping,
    Pong,
    Reload,
    Reloaded,
    Result,
)
from protocol.cli import (
    CONFIG_ENV,
    Endpoint,
    ErrorKind,
    ExitCode,
    Layer,
    Parser,
    ParserError,
    UsageError,
    env_token_layer,
    json_error,
    resolve_token,
    version_text,
)
from protocol.image_files import (
    check_overlay_path,
)
from protocol.result_view import result_json, result_view

from ..app import App
from ..cameras import RecordingError, RecordingReader
from ..config import (
    CellConfig,
    ConfigError,
    ConsoleSettings,
    LineSettings,
    ListenError,
    ModbusSettings,
    OpcUaSettings,
    PortClash,
    ServerSettings,
    check_distinct,
    enabled_listeners,
    exposure_warnings,
    load_config,
)
from ..frontends import MqttSpoolError
from ..process import PROCESS_ENV, decoder_limits, loop_factory
from ..results import is_database_url
from ..service import Catalog, Images, InspectReply, InspectRequest, builtin_catalog
from . import hash_secret as hash_secret_cli
from . import history as history_cli
from . import record as record_cli
from . import replay as replay_cli
from . import sensor_check as sensor_check_cli
from . import train as train_cli
from .admin import AdminError, call_endpoint, resolve
from .offline import file_request, image_payload, offline_service
from .results import describe_health, results_command

log = logging.getLogger("vision_server")
PROG = "vision-server"


def _config_path(args: argparse.Namespace) -> str | None:
    """--config, else $CELLVISION_CONFIG (set but empty: none)."""
    return getattr(args, "config", None) or os.environ.get(CONFIG_ENV) or None


def _fail(args: argparse.Namespace, kind: ErrorKind, message: str, code: str | None = None) -> int:
    """Report an error (JSON on stdout with --json, else one line on stderr); its exit code."""
    if getattr(args, "json", False):
        print(json.dumps(json_error(kind, message, code)))
    else:
        label = f"{code}: " if code else ""
        print(f"{PROG} {args.command}: {label}{message}", file=sys.stderr, flush=True)
    return int(kind.exit_code)


def _read_text(path: str) -> str:
    return Path(path).read_text(encoding="utf-8")


def _deprecated_token(args: argparse.Namespace) -> str | None:
    literal: str | None = getattr(args, "auth_token", None)
    if literal is not None:
        print(
            f"{PROG}: warning: --auth-token is deprecated (the token shows in ps); "
            "use --token-file PATH or $CELLVISION_TOKEN_FILE",
            file=sys.stderr,
            flush=True,
        )
    return literal


# ----------------------------------------------------------------------------- serve


def _serve(args: argparse.Namespace) -> int:
    config_path = _config_path(args)
    runtime = None
    if config_path:
        from ..service import CellRuntime

        try:
            # OpenCV fixes its image-size limits when it loads: settle them (perhaps by
            # re-executing) before the runtime opens cameras and the result log.
            limit = load_config(config_path).server.max_image_pixels
            decoder_limits.ensure(limit, argv=args.reexec_argv, process_env=PROCESS_ENV)
            runtime = CellRuntime(config_path)
        except ConfigError as exc:
            return _fail(args, ErrorKind.USAGE, f"invalid configuration: {exc}")
        base = runtime.config.server
        catalog = runtime.catalog
    else:
        base = ServerSettings()
        catalog = builtin_catalog()
    try:
        settings = _serve_settings(args, base)
        frontends = _serve_frontends(args, None if runtime is None else runtime.config, config_path)
        # The command line may move a front-end onto another's port: the file's rule again,
        # before anything binds.
        check_distinct(
            enabled_listeners(
                settings,
                console=frontends.console,
                line=frontends.line,
                modbus=frontends.modbus,
                opcua=frontends.opcua,
            )
        )
    except UsageError as exc:
        if runtime is not None:
            runtime.close()
        return _fail(args, ErrorKind.USAGE, str(exc))
    except PortClash as exc:
        if runtime is not None:
            runtime.close()
        given = ", ".join(_port_options_given(args)) or "the command line"
        return _fail(args, ErrorKind.USAGE, f"invalid configuration with {given}: {exc}")
    decoder_limits.ensure(settings.max_image_pixels, argv=args.reexec_argv, process_env=PROCESS_ENV)

    def reload() -> Catalog:
        """Every way in (SIGHUP, RELOAD) comes here, in a thread of the service. A reload done
        is said once, on stdout, when its catalog is served (``announce_reload``); a refused
        one is logged by whoever asked."""
        assert runtime is not None
        return runtime.reload()  # its notes (restart needed) are logged as warnings

    def announce_reload(catalog: Catalog) -> None:
        print(f"{PROG}: configuration reloaded (config hash {catalog.config_hash})", flush=True)

    async def main() -> int:
        app = App(
            catalog,
            settings,
            results=None if runtime is None else runtime.results,
            reloader=None if runtime is None else reload,
            line=frontends.line,
            console=frontends.console,
            config_path=None if runtime is None else runtime.path,
            modbus=frontends.modbus,
            opcua=frontends.opcua,
            mqtt=None if runtime is None else runtime.config.mqtt,
        )
        app.service.on_reloaded = announce_reload
        try:
            await app.start()
        except ListenError as exc:  # port in use, address not on this machine, no permission
            print(f"{PROG}: {exc}", file=sys.stderr)
            return int(ExitCode.CONNECTION)
        except MqttSpoolError as exc:  # a corrupt or unwritable spool file, named
            print(f"{PROG}: {exc}", file=sys.stderr)
            return int(ExitCode.USAGE)
        for warning in exposure_warnings(settings, app.listening()):
            log.warning("%s", warning)
        if runtime is None:
            names = ", ".join(sorted(catalog.inspections))
            print(
                f"{PROG}: no --config or ${CONFIG_ENV}: serving the built-in demo inspection "
                f"({names}: mean brightness of an image sent with the request); reload is off",
                file=sys.stderr,
                flush=True,
            )
        stop = asyncio.Event()
        # SIGHUP reloads through the service, the path of RELOAD (in a thread).
        app.install_signals(stop, reload=runtime is not None)
        # Only now: whoever waits for this line may signal the server at once.
        print(f"vision-server listening on {settings.host}:{app.port}", flush=True)
        if app.http is not None:  # the line right after (make demo reads both)
            print(f"{PROG}: web console on {app.http.url}", flush=True)
        if app.line is not None:
            line = app.line.settings
            print(f"{PROG}: line protocol on {line.host}:{app.line.port}", flush=True)
        if app.modbus is not None:
            modbus = app.modbus.settings
            print(f"{PROG}: Modbus TCP on {modbus.host}:{app.modbus.port}", flush=True)
        if app.opcua is not None:
            print(f"{PROG}: OPC UA on {app.opcua.endpoint}", flush=True)
        if app.mqtt is not None:
            print(f"{PROG}: MQTT to {app.mqtt.broker}", flush=True)
        await stop.wait()
        await app.stop()
        return 0

    try:
        with asyncio.Runner(loop_factory=loop_factory(settings.event_loop)) as runner:
            return runner.run(main())
    finally:
        if runtime is not None:
            runtime.close()


def _serve_settings(args: argparse.Namespace, base: ServerSettings) -> ServerSettings:
    """The configuration's settings with the command line's and the environment's on top.
    The token: --token-file, else $CELLVISION_TOKEN / $CELLVISION_TOKEN_FILE, else the
    configuration; one that is empty is an error (raises :class:`UsageError`), never "none"."""
    overrides: dict[str, Any] = {}
    if args.host is not None:
        overrides["host"] = args.host
    if args.port is not None:
        overrides["port"] = args.port
    cli = Layer("command line", token=_deprecated_token(args), token_file=args.token_file)
    token, source = resolve_token(
        cli,
        env_token_layer(os.environ),
        Layer("configuration", token=base.auth_token),
        read_text=_read_text,
    )
    overrides["auth_token"] = token
    if source is not None:
        log.info("clients must present the token from %s", source)
    return ServerSettings(**{**base.__dict__, **overrides})


@dataclass(frozen=True)
class _Frontends:
    """The optional front-ends' sections as ``serve`` runs them (None: the built-in demo)."""

    console: ConsoleSettings | None
    line: LineSettings | None
    modbus: ModbusSettings | None
    opcua: OpcUaSettings | None


FRONTEND_OPTIONS = (
    ("console", "the web console"),
    ("line", "the line protocol"),
    ("modbus", "Modbus TCP"),
    ("opcua", "OPC UA"),
)
"""Each optional front-end: its section (and option) name, and what it is, for messages."""


def _serve_frontends(
    args: argparse.Namespace, config: CellConfig | None, path: str | None
) -> _Frontends:
    """The configuration's ``console:``, ``line:`` and ``modbus:`` sections with the command
    line on top: ``--no-NAME`` switches one off, ``--NAME-port N`` moves one the configuration
    enables; a port for one it does not enable is an error (raises :class:`UsageError`)."""
    sections: dict[str, Any] = {}
    for name, what in FRONTEND_OPTIONS:
        section = None if config is None else getattr(config, name)
        port: int | None = getattr(args, f"{name}_port", None)
        if getattr(args, f"no_{name}", False):
            section = None if section is None else dataclasses.replace(section, enabled=False)
        elif port is not None:
            if section is None:
                raise UsageError(
                    f"--{name}-port: the built-in demo (no --config or ${CONFIG_ENV}) serves "
                    f"the binary protocol only; give a configuration that enables {what} "
                    f"({name}.enabled: true)"
                )
            if not section.enabled:
                raise UsageError(
                    f"--{name}-port: {what} is off in {path} ({name}.enabled is not true); "
                    f"enable it there ({name}: {{enabled: true}}) to give it a port here"
                )
            section = dataclasses.replace(section, port=port)
        sections[name] = section
    return _Frontends(**sections)


def _port_options_given(args: argparse.Namespace) -> list[str]:
    """The listening options given on the command line, for a port clash's message."""
    given = [f"--{name}" for name in ("host", "port") if getattr(args, name, None) is not None]
    for name, _ in FRONTEND_OPTIONS:
        if getattr(args, f"{name}_port", None) is not None:
            given.append(f"--{name}-port")
    return given


def _port(text: str) -> int:
    """A TCP port option: 0..65535, as the file's ``port`` keys (0: any free port)."""
    try:
        port = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a port in 0..65535, got {text!r}") from None
    if not 0 <= port < 65536:
        raise argparse.ArgumentTypeError(f"expected a port in 0..65535, got {port}")
    return port


# ----------------------------------------------------------------------------- check-config


def _check_config(args: argparse.Namespace) -> int:
    console = Console()
    args.file = args.file or _config_path(args)
    if not args.file:
        return _fail(args, ErrorKind.USAGE, f"give the configuration FILE (or ${CONFIG_ENV})")
    if not Path(args.file).is_file():
        return _fail(args, ErrorKind.USAGE, f"no such file: {args.file}")
    try:
        from ..service import check_result_log

        config = load_config(args.file)
        check_result_log(config)  # a log that cannot be created would stop `serve`
    except ConfigError as exc:
        if args.json:
            print(
                # The one error shape of --json (docs/integrator-guide.md §6), with the file's
                # line and key path beside the message.
                json.dumps(
                    {
                        "valid": False,
                        "error": {
                            **json_error(ErrorKind.USAGE, str(exc))["error"],
                            "line": exc.line,
                            "path": exc.path,
                        },
                    }
                )
            )
        else:
            Console(stderr=True).print(
                Text("invalid: ", style="red") + Text(str(exc)), soft_wrap=True
            )
        # A configuration error, as serve, run and modbus-map report one (and as --json's
        # error kind "usage" says): exit 2, not the fail verdict's 1.
        return int(ErrorKind.USAGE.exit_code)
    if args.json:
        print(json.dumps(_summary(config)))
        return 0
    table = Table(title=Text(f"{args.file}: valid (config hash {config.config_hash})"))
    if not config.inspections:
        Console(stderr=True).print(
            Text("warning: ", style="yellow")
            + Text("no inspections: the server would answer every INSPECT UNKNOWN_INSPECTION"),
            soft_wrap=True,
        )
    for column in ("inspection", "type", "camera", "source", "roi"):
        table.add_column(column)
    for inspection in config.inspections:
        settings = config.cameras[inspection.camera]
        source = next(k for k, v in _sources().items() if isinstance(settings, v))
        roi = getattr(getattr(inspection, "common", None), "roi", None)
        cells = (inspection.name, inspection.type, inspection.camera, source)
        table.add_row(*map(Text, cells), Text("whole image" if roi is None else str(list(roi))))
    console.print(table)
    return 0


def _modbus_map(args: argparse.Namespace) -> int:
    from .modbus_map import map_json, print_map

    args.file = args.file or _config_path(args)
    if not args.file:
        return _fail(args, ErrorKind.USAGE, f"give the configuration FILE (or ${CONFIG_ENV})")
    if not Path(args.file).is_file():
        return _fail(args, ErrorKind.USAGE, f"no such file: {args.file}")
    try:
        config = load_config(args.file)
    except ConfigError as exc:
        return _fail(args, ErrorKind.USAGE, str(exc))  # exit 2, as check-config
    if args.json:
        print(json.dumps(map_json(config)))
    else:
        print_map(config, args.file, stdout_console())
    return 0


def _sources() -> dict[str, type]:
    from ..cameras import SOURCE_NAMES

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
    """The inspection offline on each ``--image`` in turn, through the server's own request
    path; the exit code is the worst of theirs (an error, then a fail verdict, then pass)."""
    config_path = _config_path(args)
    if not config_path:
        return _fail(args, ErrorKind.USAGE, f"give --config FILE (or ${CONFIG_ENV})")
    try:
        config = load_config(config_path)
    except ConfigError as exc:
        return _fail(args, ErrorKind.USAGE, f"invalid configuration: {exc}")
    inspection = next((i for i in config.inspections if i.name == args.inspection), None)
    if inspection is None:
        return _fail(
            args,
            ErrorKind.USAGE,
            f"no inspection named {args.inspection!r}; configured: "
            f"{', '.join(i.name for i in config.inspections)}",
        )
    if args.recording is not None:
        return _run_recording(args, config, inspection)
    if args.frame:
        return _fail(args, ErrorKind.USAGE, "--frame goes with --recording")
    if len(args.image) > 1 and args.depth:
        return _fail(args, ErrorKind.USAGE, "--depth frames go with one --image, not several")
    if len(args.image) > 1 and args.overlay is not None:
        return _fail(args, ErrorKind.USAGE, "--overlay takes one --image (one file, one overlay)")
    limit = config.server.max_image_pixels
    try:
        suffix = None
        if args.overlay is not None:
            suffix = check_overlay_path(args.overlay, folder_exists=os.path.isdir)
        # The configured limit is the server's own check (headers, descriptors), as served.
        # OpenCV's decoders must not refuse below it (a larger limit may re-execute); not
        # lowered to it either, so that a large BMP is IMAGE_TOO_LARGE like a PNG, not an
        # undecodable file.
        decoder_limits.ensure(
            max(limit, decoder_limits.DEFAULT_MAX_IMAGE_PIXELS), argv=args.reexec_argv
        )
        depth = tuple(image_payload(Path(p), ImageRole.DEPTH) for p in args.depth)
        colours = [(p, image_payload(Path(p), ImageRole.COLOR)) for p in args.image]
    except ValueError as exc:
        return _fail(args, ErrorKind.USAGE, str(exc))
    service = offline_service(
        inspection,
        config.cameras[inspection.camera],
        config.base_dir,
        config_hash=config.config_hash,
        max_image_pixels=limit,
    )
    console = Console()

    async def each() -> ExitCode:
        worst = ExitCode.OK
        try:
            for path, colour in colours:
                request = file_request(inspection.name, colour, depth, overlay=suffix)
                try:
                    reply = await service.inspect(request)
                except CellvisionError as exc:
                    worst = max(worst, _image_error(args, path, exc))
                    continue
                _show_result(args, console, reply, path)
                worst = max(worst, ExitCode.OK if reply.passed else ExitCode.FAILED)
                if suffix is not None:
                    worst = max(worst, _write_overlay(args, reply))
        finally:
            service.close()
        return worst

    return int(asyncio.run(each()))


def _run_recording(args: argparse.Namespace, config: CellConfig, inspection: Any) -> int:
    """``run --recording DIR``: the inspection on the recording's frames, ``inspection.frames``
    consecutive frames a run (the first one's colour, every one's depth), as a ``recording``
    camera would give them; each run reported as an image's is."""
    if args.depth:
        return _fail(args, ErrorKind.USAGE, "--depth goes with --image: a recording has its own")
    try:
        recording = RecordingReader(args.recording)
    except RecordingError as exc:
        return _fail(args, ErrorKind.USAGE, str(exc))
    group = max(1, int(inspection.frames))
    total = len(recording)
    starts = list(args.frame) or list(range(0, total - group + 1, group))
    for start in starts:
        if not 0 <= start <= total - group:
            return _fail(
                args,
                ErrorKind.USAGE,
                f"--frame {start}: the recording has {total} frames (0..{total - 1}) and "
                f"{inspection.name} takes {group} at a time",
            )
    if not starts:
        return _fail(
            args,
            ErrorKind.USAGE,
            f"{args.recording}: {total} frames, {inspection.name} takes {group} at a time",
        )
    if len(starts) > 1 and args.overlay is not None:
        return _fail(args, ErrorKind.USAGE, "--overlay takes one run: give one --frame")
    try:
        suffix = None
        if args.overlay is not None:
            suffix = check_overlay_path(args.overlay, folder_exists=os.path.isdir)
    except ValueError as exc:
        return _fail(args, ErrorKind.USAGE, str(exc))
    service = offline_service(
        inspection,
        config.cameras[inspection.camera],
        config.base_dir,
        config_hash=config.config_hash,
        max_image_pixels=config.server.max_image_pixels,
        intrinsics=recording.intrinsics,
    )
    console = Console()

    async def each() -> ExitCode:
        worst = ExitCode.OK
        try:
            for number, start in enumerate(starts, start=1):
                name = str(recording.path / recording.entries[start].color)
                try:
                    # One run's frames at a time: a recording is never all in memory.
                    frames = [recording.read(i) for i in range(start, start + group)]
                except RecordingError as exc:
                    worst = max(worst, ExitCode(_fail(args, ErrorKind.USAGE, str(exc))))
                    continue
                depth = tuple(f.depth for f in frames if f.depth is not None)
                images = Images(frames[0].color8(), depth if inspection.uses_depth else ())
                request = InspectRequest(
                    inspection.name, images, overlay=suffix, peer="offline", request_id=number
                )
                try:
                    reply = await service.inspect(request)
                except CellvisionError as exc:
                    worst = max(worst, _image_error(args, name, exc))
                    continue
                _show_result(args, console, reply, name, frame=start)
                worst = max(worst, ExitCode.OK if reply.passed else ExitCode.FAILED)
                if suffix is not None:
                    worst = max(worst, _write_overlay(args, reply))
        finally:
            service.close()
        return worst

    return int(asyncio.run(each()))


def _image_error(args: argparse.Namespace, image: str, exc: CellvisionError) -> ExitCode:
    """Report the error of one image's run; its exit code."""
    if args.json:
        print(
            json.dumps({"image": image, **json_error(ErrorKind.SERVER, exc.message, exc.code.name)})
        )
    else:
        print(f"{PROG} run: {image}: {exc.code.name}: {exc.message}", file=sys.stderr, flush=True)
    return ExitCode.SERVER


def _show_result(
    args: argparse.Namespace,
    console: Console,
    reply: InspectReply,
    image: str,
    *,
    frame: int | None = None,
) -> None:
    if args.json:  # one object per image, one per line; full precision
        shown = Result(
            0, reply.inspection, reply.passed, reply.data, reply.timing, reply.camera
        )  # the one --json shape of both tools (protocol.result_view)
        out = result_json(shown, image=image)
        if frame is not None:  # a recording's run: the frame it started at
            out = {**out, "frame": frame}
        print(json.dumps(out))
        return
    title = Text(f"{image}: " if frame is None else f"{image} (frame {frame}): ")
    title.append_text(_verdict_text(reply.passed))
    title.append(f" {reply.inspection} on {reply.camera}")
    title.append(f" ({reply.compute_ms:.1f} ms)", style="dim")
    console.print(title, soft_wrap=True)  # a long path stays on its line, with its verdict
    print_result_data(console, reply.data)


def _write_overlay(args: argparse.Namespace, reply: InspectReply) -> ExitCode:
    """Write the overlay to --overlay (its folder and extension were checked before the run;
    the service encoded it in that format)."""
    path = str(args.overlay)
    if reply.overlay is None or reply.overlay.encoded is None:
        print(
            f"{PROG} run: {reply.inspection} drew no overlay; nothing written to {path}",
            file=sys.stderr,
        )
        return ExitCode.OK
    try:
        Path(path).write_bytes(reply.overlay.encoded)
    except OSError as exc:
        message = exc.strerror or str(exc)
        return ExitCode(_fail(args, ErrorKind.USAGE, f"--overlay {path}: cannot write: {message}"))
    if not args.json:
        print(f"overlay written to {path}")
    return ExitCode.OK


def _verdict_text(passed: bool) -> Text:
    return Text("PASS", style="bold green") if passed else Text("FAIL", style="bold red")


def print_result_data(console: Console, data: dict[str, Any]) -> None:
    """A result's data for people: fields, then one table per list (features, corners, ...),
    rounded (see :mod:`protocol.result_view`). Every text goes in as Text, never as markup."""
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


# ----------------------------------------------------------------------------- test-inspections


def _test_inspections(args: argparse.Namespace) -> int:
    """Golden cases (inspection + images + expected results) through the serving code path."""
    from .golden import golden_command

    if args.from_recording is not None:
        return _case_from_recording(args)
    given = [f"--{n}" for n in ("inspection", "out") if getattr(args, n) is not None]
    if given or args.frame:
        return _fail(
            args, ErrorKind.USAGE, f"{(given or ['--frame'])[0]} goes with --from-recording"
        )
    return golden_command(args.paths, json_out=args.json, update=args.update)


def _case_from_recording(args: argparse.Namespace) -> int:
    """``test-inspections --from-recording DIR --inspection NAME --out CASE``: make the case,
    report it as a run with --update is reported."""
    from .golden import Report, case_from_recording, print_report, report_json

    config_path = _config_path(args)
    missing = [f"--{n}" for n in ("inspection", "out") if getattr(args, n) is None]
    if missing:
        return _fail(args, ErrorKind.USAGE, f"--from-recording needs {' and '.join(missing)}")
    if not config_path:
        return _fail(
            args, ErrorKind.USAGE, f"--from-recording needs --config FILE (or ${CONFIG_ENV})"
        )
    if args.paths or args.update:
        return _fail(args, ErrorKind.USAGE, "--from-recording makes one case: no PATH, no --update")
    try:
        case = case_from_recording(
            Path(args.from_recording),
            Path(config_path),
            args.inspection,
            Path(args.out),
            frames=args.frame,
        )
    except ConfigError as exc:
        return _fail(args, ErrorKind.USAGE, str(exc))
    report = Report([case], updated=True)
    if args.json:
        print(json.dumps(report_json(report)))
    else:
        print_report(report, Console())
        if report.exit_code == 0:
            print(
                f"case written to {args.out}: review its expected.yaml, then run "
                f"`vision-server test-inspections {args.out}`"
            )
    return report.exit_code


# ----------------------------------------------------------------------------- results, admin


def _log_target(text: str) -> str | Path:
    """``--db``: a PostgreSQL URL stays text, anything else is an SQLite file's path."""
    return text if is_database_url(text) else Path(text)


def _results(args: argparse.Namespace) -> int:
    db = args.db
    if db is None:
        config_path = _config_path(args)
        if not config_path:
            return _fail(
                args, ErrorKind.USAGE, f"give --db PATH or --config FILE (or ${CONFIG_ENV})"
            )
        try:
            config = load_config(config_path)
        except ConfigError as exc:
            return _fail(args, ErrorKind.USAGE, f"invalid configuration: {exc}")
        if not config.results.enabled:
            return _fail(args, ErrorKind.USAGE, "the result log is disabled in the configuration")
        db = config.results.url or config.results.path
        names = [i.name for i in config.inspections]
        if args.inspection is not None and args.inspection not in names:
            # Still asked: the log may hold an inspection that has since been renamed.
            Console(stderr=True).print(
                Text("warning: ", style="yellow")
                + Text(
                    f"{args.inspection!r} is not an inspection of {config_path} "
                    f"(its inspections: {', '.join(names) or 'none'})"
                ),
                soft_wrap=True,
            )
    return results_command(
        db,
        since=args.since,
        inspection=args.inspection,
        json_out=args.json,
        limit=args.limit,
        failed_only=args.failed,
        console=stdout_console(),
    )


def _endpoint(args: argparse.Namespace) -> Endpoint:
    cli = Layer(
        "command line",
        server=args.server,
        token=_deprecated_token(args),
        token_file=args.token_file,
        tls=args.tls,
        ca_file=args.ca,
    )
    return resolve(cli, _config_path(args))


def _admin(
    args: argparse.Namespace, build: Callable[[int], Message], default_timeout_s: float
) -> tuple[Message, str] | int:
    """Send one request to the server: (its answer, "host:port"), or the exit code of an error
    already reported."""
    try:
        endpoint = _endpoint(args)
    except UsageError as exc:
        return _fail(args, ErrorKind.USAGE, str(exc))
    where = f"{endpoint.host}:{endpoint.port}"
    timeout_s = args.timeout if args.timeout is not None else default_timeout_s
    try:
        return call_endpoint(endpoint, build, timeout_s=timeout_s), where
    except UsageError as exc:
        return _fail(args, ErrorKind.USAGE, str(exc))
    except AdminError as exc:
        return _fail(args, ErrorKind.CONNECTION, f"{where}: {exc}")
    except CellvisionError as exc:
        return _fail(args, ErrorKind.SERVER, f"{where}: {exc.message}", exc.code.name)


def _ping(args: argparse.Namespace) -> int:
    done = _admin(args, lambda rid: Ping(rid, "health"), 3.0)
    if isinstance(done, int):
        return done
    answer, where = done
    assert isinstance(answer, Pong)
    healthy = answer.healthy
    if args.json:
        print(
            json.dumps(
                {"server": where, "answers": True, "healthy": healthy, "health": answer.health}
            )
        )
    elif healthy:
        print(f"{where} answers; healthy: {describe_health(answer.health)}")
    else:
        print(
            f"vision-server ping: {where} answers but is UNHEALTHY: "
            + describe_health(answer.health),
            file=sys.stderr,
        )
    # Exit 1 (the fail verdict) is also Docker's HEALTHCHECK code for unhealthy.
    return int(ExitCode.OK if healthy else ExitCode.FAILED)


def _reload(args: argparse.Namespace) -> int:
    done = _admin(args, Reload, 10.0)
    if isinstance(done, int):
        return done
    answer, where = done
    assert isinstance(answer, Reloaded)
    if args.json:
        print(
            json.dumps(
                {
                    "server": where,
                    "config_hash": answer.config_hash,
                    "inspections": [i.get("name") for i in answer.inspections],
                    "notes": list(answer.notes),
                }
            )
        )
        return int(ExitCode.OK)
    names = ", ".join(str(i.get("name")) for i in answer.inspections)
    print(f"{where} reloaded: config hash {answer.config_hash}; inspections: {names}")
    for note in answer.notes:  # what the reload did not do, e.g. a restart is needed
        print(f"note: {note}")
    return int(ExitCode.OK)


def _options(*, top: bool, server: bool = True) -> Parser:
    """Options accepted before and after the command: on the main parser (``top``) with their
    defaults, on a command without, so that a value given before the command is kept."""
    unset = None if top else argparse.SUPPRESS
    parent = Parser(add_help=False)
    parent.add_argument(
        "--config", default=unset, help=f"cell configuration (default ${CONFIG_ENV})"
    )
    parent.add_argument(
        "--json",
        action="store_true",
        default=False if top else argparse.SUPPRESS,
        help="machine-readable output (errors too)",
    )
    if not server:
        return parent
    group = parent.add_argument_group("reaching the server (ping, reload)")
    group.add_argument(
        "--server", default=unset, help="HOST:PORT (default $CELLVISION_SERVER, the config)"
    )
    group.add_argument(
        "--token-file",
        default=unset,
        metavar="PATH",
        help="file holding the token (default $CELLVISION_TOKEN(_FILE), the config)",
    )
    group.add_argument(
        "--tls",
        action="store_true",
        default=None if top else argparse.SUPPRESS,
        help="connect with TLS (default $CELLVISION_TLS, the config)",
    )
    group.add_argument(
        "--ca",
        metavar="FILE",
        default=unset,
        help="trust this CA or certificate (PEM); implies --tls (default $CELLVISION_CA)",
    )
    group.add_argument("--timeout", type=float, default=unset, help="seconds (ping 3, reload 10)")
    # Deprecated: a token on the command line is visible to every user through ps.
    group.add_argument("--auth-token", default=unset, help=argparse.SUPPRESS)
    return parent


def build_parser() -> argparse.ArgumentParser:
    parser = Parser(
        prog=PROG,
        description=__doc__,
        formatter_class=argparse.RawTextHelpFormatter,
        parents=[_options(top=True)],
    )
    parser.add_argument(
        "-v", "--verbose", action="store_true", help="log each connection; OpenCV's own messages"
    )
    parser.add_argument("--version", action="version", version=version_text(PROG))
    common = _options(top=False)
    local = _options(top=False, server=False)
    sub = parser.add_subparsers(dest="command", required=True)

    serve = sub.add_parser(
        "serve",
        parents=[local],
        help="serve inspections over TCP",
        description="Without --config or $CELLVISION_CONFIG: a built-in demo inspection. "
        "The token clients must present: --token-file, else $CELLVISION_TOKEN or "
        "$CELLVISION_TOKEN_FILE, else the configuration's server.auth_token(_file). "
        "The listening options override the configuration's keys for this run (the file is "
        "not changed); no two front-ends may share a port (exit 2, both keys named). Each "
        "front-end's bound port is printed once it listens (useful with 0: any free port).",
    )
    serve.add_argument(
        "--host", default=None, help="the binary protocol's address (default: server.host)"
    )
    serve.add_argument(
        "--port",
        type=_port,
        default=None,
        metavar="N",
        help="the binary protocol's TCP port (default: server.port, 7878; 0: any)",
    )
    for name, what in FRONTEND_OPTIONS:
        # The front-end must be enabled in the configuration: a port option does not enable
        # one (its other keys, e.g. Modbus's unit_id, live in the file).
        choice = serve.add_mutually_exclusive_group()
        choice.add_argument(
            f"--{name}-port",
            type=_port,
            default=None,
            metavar="N",
            help=f"{what}'s port (default: {name}.port; 0: any); the file must enable it",
        )
        choice.add_argument(
            f"--no-{name}",
            action="store_true",
            help=f"do not start {what}, even if the configuration enables it",
        )
    serve.add_argument(
        "--token-file", metavar="PATH", default=None, help="require the token in this file"
    )
    # Deprecated: a token on the command line is visible to every user through ps.
    serve.add_argument("--auth-token", default=None, help=argparse.SUPPRESS)
    serve.set_defaults(func=_serve)

    check = sub.add_parser("check-config", parents=[local], help="validate a configuration file")
    check.add_argument("file", nargs="?", help=f"the configuration (default ${CONFIG_ENV})")
    check.set_defaults(func=_check_config)

    run = sub.add_parser(
        "run", parents=[local], help="run one inspection offline on image files or a recording"
    )
    run.add_argument("inspection")
    images = run.add_mutually_exclusive_group(required=True)
    images.add_argument(
        "--image",
        action="append",
        help="colour or gray image, 8-bit, any format OpenCV reads (PNG, JPEG, BMP, TIFF, "
        "WebP, PGM, ...); repeat to run on each in turn (one result each; exit code: the worst)",
    )
    images.add_argument(
        "--recording",
        metavar="DIR",
        help="a recording (vision-server record): run on its frames in turn, with their depth "
        "and the recording's intrinsics (the configuration's when it gives them); an "
        "inspection that takes N frames (qr_pose: frames, default 5) takes N at a time, as "
        "from the camera",
    )
    run.add_argument(
        "--frame",
        action="append",
        type=int,
        default=[],
        metavar="N",
        help="with --recording: run only from frame N (0-based); repeat for more",
    )
    run.add_argument(
        "--depth",
        action="append",
        default=[],
        help="depth image, 16-bit gray in mm (PNG, TIFF, PGM, ...); repeat for more frames",
    )
    run.add_argument(
        "--overlay",
        metavar="PATH",
        help="write the overlay image here (.png, .jpg, ...; the folder must exist)",
    )
    run.set_defaults(func=_run)

    golden = sub.add_parser(
        "test-inspections",
        parents=[local],
        help="check inspections against known images (golden cases)",
    )
    golden.add_argument(
        "paths", nargs="*", help="case folders or folders of cases (default: test_inspections)"
    )
    golden.add_argument(
        "--update",
        action="store_true",
        help="rewrite expected.yaml from the results, show the diff",
    )
    made = golden.add_argument_group(
        "making a case from a recording (needs --config; expected.yaml is what the "
        "inspection gives now: review it)"
    )
    made.add_argument(
        "--from-recording", metavar="DIR", help="the recording (vision-server record)"
    )
    made.add_argument("--inspection", metavar="NAME", help="the configuration's inspection")
    made.add_argument("--out", metavar="CASE", help="the new case folder")
    made.add_argument(
        "--frame",
        action="append",
        type=int,
        default=[],
        metavar="N",
        help="only the run from frame N (0-based); repeat for more (default: every frame)",
    )
    golden.set_defaults(func=_test_inspections)

    results = sub.add_parser("results", parents=[local], help="list logged inspection results")
    results.add_argument(
        "--db",
        type=_log_target,
        help="the result log: an SQLite file, or a postgresql://user@host:port/db URL",
    )
    results.add_argument("--since", help="e.g. 10m, 2h, 1d or an ISO date/time")
    results.add_argument("--inspection")
    results.add_argument("--failed", action="store_true", help="only failed inspections")
    results.add_argument("--limit", type=int, default=100)
    results.set_defaults(func=_results)

    sensor_check_cli.add_parser(sub, [local])
    record_cli.add_parser(sub, [local])
    history_cli.add_parser(sub, [local])
    replay_cli.add_parser(sub, [local])
    hash_secret_cli.add_parser(sub, [local])

    modbus_map = sub.add_parser(
        "modbus-map",
        parents=[local],
        help="print the Modbus register map of a configuration (for the PLC programmer)",
    )
    modbus_map.add_argument("file", nargs="?", help=f"the configuration (default ${CONFIG_ENV})")
    modbus_map.set_defaults(func=_modbus_map)

    ping = sub.add_parser(
        "ping", parents=[common], help="check that a server answers (the container health check)"
    )
    ping.set_defaults(func=_ping)

    reload = sub.add_parser(
        "reload", parents=[common], help="ask a running server to re-read its configuration"
    )
    reload.set_defaults(func=_reload)
    train_cli.add_parser(sub, [common], _reload)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    # Rich ends a closed pipe with exit 1 (our "fail"): let it reach the one handler below.
    Console.on_broken_pipe = _broken_pipe  # type: ignore[method-assign,assignment]
    try:
        return _main(argv)
    except KeyboardInterrupt:
        # Ctrl-C in a command (serve ends cleanly on its own): one line, not a traceback.
        print("vision-server: interrupted", file=sys.stderr)
        return int(ExitCode.INTERRUPTED)
    except BrokenPipeError:
        return quiet_broken_pipe()


def stdout_console() -> Console:
    """The console for tables on stdout. Into a file or a pipe Rich assumes 80 columns and cuts
    names and times ("inspecti…"); there a table gets the width it needs (up to 200)."""
    return Console() if sys.stdout.isatty() else Console(width=200)


def _broken_pipe(console: Console) -> None:
    raise BrokenPipeError


def quiet_broken_pipe() -> int:
    """The reader of stdout went away (``| head``): end without a traceback. stdout now points
    at /dev/null, so that Python's flush at exit does not fail again. The exit code is a shell's
    for a command killed by SIGPIPE."""
    devnull = os.open(os.devnull, os.O_WRONLY)
    os.dup2(devnull, sys.stdout.fileno())
    os.close(devnull)
    return 128 + signal.SIGPIPE


def quiet_opencv(verbose: bool) -> None:
    """Silence OpenCV's own ``[ WARN:...]`` and ``[ERROR:...]`` lines: every failure they
    announce reaches the user as our own error. Kept with ``--verbose`` or a given
    $OPENCV_LOG_LEVEL."""
    if not verbose and "OPENCV_LOG_LEVEL" not in os.environ:
        cv2.utils.logging.setLogLevel(cv2.utils.logging.LOG_LEVEL_SILENT)


def _main(argv: Sequence[str] | None) -> int:
    # Run as a program (not called from Python), serve may re-execute itself: decoder_limits.
    reexec_argv = list(sys.orig_argv) if argv is None else None
    argv = list(sys.argv[1:] if argv is None else argv)
    try:
        args = build_parser().parse_args(argv)
    except ParserError as exc:
        if "--json" in argv:
            print(json.dumps(json_error(ErrorKind.USAGE, str(exc))))
        else:
            exc.parser.print_usage(sys.stderr)
            print(f"{exc.parser.prog}: error: {exc}", file=sys.stderr)
        return int(ExitCode.USAGE)
    args.reexec_argv = reexec_argv
    quiet_opencv(args.verbose)
    logging.basicConfig(
        level=logging.INFO if args.verbose else logging.WARNING,
        format="%(asctime)s %(name)s %(levelname)s %(message)s",
        stream=sys.stderr,
    )
    # What people did through the console (saves, reverts, operators' answers) is the cell's
    # record: in the log whatever the verbosity (vision_server/frontends/http_common.py).
    logging.getLogger("vision_server.audit").setLevel(logging.INFO)
    return int(args.func(args))


if __name__ == "__main__":
    sys.exit(main())
