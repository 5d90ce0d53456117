"""``vision-server replay``: which stored verdicts a changed configuration would flip.

    vision-server replay INSPECTION --config changed.yaml [--last N] [--json]
                         [--db LOG] [--running cell.yaml] [--deadline S]

The command line's side of the console's impact preview (docs/console.md, "Impact before
save"), by the same engine (:func:`vision_server.service.replay`): INSPECTION as
``changed.yaml`` configures it is run, offline (no server needed), on the newest stored images
of INSPECTION in the result log that ``changed.yaml``'s ``results:`` section names (or
``--db``), read-only, so it runs safely beside the server writing to it.

"Current configuration": a row stored under another configuration than the running one is
marked (its flip may come from that older change). The running configuration is ``--running
FILE``'s when given, else the one the newest production result of INSPECTION was made under.

Exit codes: 0 no verdict flips; 1 at least one verdict flips; 2 usage or configuration error
(an invalid ``changed.yaml``, an unknown inspection, no result log, no stored image of the
inspection: nothing replayed); 4 one or more stored images could not be replayed (listed).
With ``--json`` the report (or the error) is one JSON object on stdout.
"""

from __future__ import annotations

import argparse
import asyncio
import json
import os
import sys
import time
from datetime import datetime
from pathlib import Path
from typing import Any

from rich.console import Console
from rich.table import Table
from rich.text import Text

from protocol.cli import CONFIG_ENV, ErrorKind, ExitCode, json_error

from ..cameras import CameraSettings, Intrinsics, SimCameraSettings, make_camera
from ..config import ConfigError, load_config
from ..process import decoder_limits
from ..results import (
    ProductionRows,
    ResultLogError,
    ResultStore,
    is_database_url,
    open_readonly,
)
from ..service import DEFAULT_LAST, MAX_LAST, ImpactReport, replay
from .offline import offline_service

__all__ = ["add_parser", "replay_command"]

DEFAULT_DEADLINE_S = 600.0
"""How long a replay may run unless ``--deadline`` says, seconds."""
PER_IMAGE_S = 30.0
"""The deadline of one image's run, seconds."""


class ReplayUsage(Exception):
    """Nothing can be replayed: ``code`` names why (exit 2)."""

    def __init__(self, code: str, message: str) -> None:
        super().__init__(message)
        self.code = code
        self.message = message


def add_parser(sub: Any, parents: list[argparse.ArgumentParser]) -> None:
    p = sub.add_parser(
        "replay",
        parents=parents,
        help="which stored verdicts a changed configuration would flip (impact before save)",
        description="Run INSPECTION as --config FILE configures it on its newest stored images "
        "in the result log of that file's results: section (or --db) and list the results "
        "whose verdict would change. Exit 0: none flips; 1: some flip; 2: usage, "
        "configuration, no log or no stored image; 4: some images could not be replayed.",
    )
    p.add_argument("inspection", help="the inspection (as the changed file configures it)")
    p.add_argument(
        "--last",
        type=int,
        default=DEFAULT_LAST,
        metavar="N",
        help=f"replay the newest N stored images (1..{MAX_LAST}, default {DEFAULT_LAST})",
    )
    p.add_argument(
        "--db",
        default=None,
        metavar="LOG",
        help="the result log (an SQLite file or a postgresql:// URL) instead of the file's",
    )
    p.add_argument(
        "--running",
        default=None,
        metavar="FILE",
        help="the configuration the server runs (default: the newest result's)",
    )
    p.add_argument(
        "--deadline",
        type=float,
        default=DEFAULT_DEADLINE_S,
        metavar="S",
        help=f"stop after S seconds, reporting what was replayed (default {DEFAULT_DEADLINE_S:g})",
    )
    p.set_defaults(func=replay_command)


def replay_command(args: argparse.Namespace) -> int:
    json_out = bool(getattr(args, "json", False))
    try:
        report = _replay(args)
    except ReplayUsage as exc:
        if json_out:
            print(json.dumps(json_error(ErrorKind.USAGE, exc.message, exc.code)))
        else:
            print(f"vision-server replay: {exc.code}: {exc.message}", file=sys.stderr, flush=True)
        return int(ExitCode.USAGE)
    if json_out:
        print(json.dumps(report.to_json()))
    else:
        _show(report)
    if report.failed:
        return int(ExitCode.SERVER)
    return int(ExitCode.FAILED if report.flipped else ExitCode.OK)


def _replay(args: argparse.Namespace) -> ImpactReport:
    path = getattr(args, "config", None) or os.environ.get(CONFIG_ENV) or None
    if not path:
        raise ReplayUsage("USAGE", f"give --config changed.yaml (or ${CONFIG_ENV})")
    if not 1 <= args.last <= MAX_LAST:
        raise ReplayUsage("USAGE", f"--last must be in 1..{MAX_LAST}, got {args.last}")
    if not args.deadline > 0:
        raise ReplayUsage("USAGE", f"--deadline must be > 0 seconds, got {args.deadline}")
    try:
        config = load_config(path)
    except (ConfigError, OSError) as exc:
        raise ReplayUsage("CONFIG_INVALID", f"invalid configuration: {exc}") from None
    inspection = next((i for i in config.inspections if i.name == args.inspection), None)
    if inspection is None:
        names = ", ".join(i.name for i in config.inspections) or "none"
        raise ReplayUsage(
            "UNKNOWN_INSPECTION", f"no inspection named {args.inspection!r}; configured: {names}"
        )
    target: str | Path | None = args.db
    if target is None:
        if not config.results.enabled:
            raise ReplayUsage(
                "NO_RESULT_LOG", f"{path} has no result log (results: path or url); give --db"
            )
        target = config.results.url or config.results.path
    elif not is_database_url(target):
        target = Path(target)
    assert target is not None
    running = None
    if args.running is not None:
        try:
            running = load_config(args.running).config_hash
        except (ConfigError, OSError) as exc:
            raise ReplayUsage("CONFIG_INVALID", f"--running: invalid: {exc}") from None
    limit = config.server.max_image_pixels
    # The server's own pixel limit; OpenCV's decoders must not refuse below it (as `run`).
    decoder_limits.ensure(
        max(limit, decoder_limits.DEFAULT_MAX_IMAGE_PIXELS), argv=getattr(args, "reexec_argv", None)
    )
    try:
        with open_readonly(target) as log:
            current = running or _newest_hash(log, inspection.name)
            settings = config.cameras[inspection.camera]
            service = offline_service(
                inspection,
                settings,
                config.base_dir,
                config_hash=config.config_hash,
                max_image_pixels=limit,
                intrinsics=_served_intrinsics(inspection.camera, settings, config.base_dir),
            )
            try:
                report = asyncio.run(
                    replay(
                        service,
                        log,
                        inspection,
                        last=args.last,
                        current_config_hash=current,
                        deadline=time.monotonic() + args.deadline,
                        per_image_s=PER_IMAGE_S,
                    )
                )
            finally:
                service.close()
    except ResultLogError as exc:
        raise ReplayUsage("NO_RESULT_LOG", str(exc)) from None
    if report.with_image == 0 and report.complete:
        raise ReplayUsage(
            "NO_IMAGES",
            f"the result log holds no stored image of {inspection.name!r} among its newest "
            f"{report.considered} production results: the log keeps the input images that "
            "results: store_images says (the default, failures, keeps failed parts' only)",
        )
    return report


def _served_intrinsics(name: str, settings: CameraSettings, base_dir: Path) -> Intrinsics | None:
    """The intrinsics the server's camera ``name`` has: the configured ones, else a simulated
    camera's, from its scene (the served camera has them, checks each image's size against
    them and hands them to the inspection: so must the replay, to give the console's verdicts)."""
    configured: Intrinsics | None = getattr(settings, "intrinsics", None)
    if configured is not None or not isinstance(settings, SimCameraSettings):
        return configured
    camera = make_camera(name, settings, base_dir=base_dir)
    try:
        return camera.intrinsics
    finally:
        camera.close()


def _newest_hash(log: ResultStore, inspection: str) -> str:
    """The configuration hash of the newest production result of ``inspection`` ("" if none):
    the configuration the line ran last."""
    rows = ProductionRows(log, inspection, page_rows=50, max_examined=1000)
    newest = next(iter(rows), None)  # among the first pages in practice
    return "" if newest is None else newest.config_hash


def _show(report: ImpactReport) -> None:
    console = Console() if sys.stdout.isatty() else Console(width=160)
    answer = report.to_json()
    head = (
        f"{report.inspection}: {report.with_image} stored images replayed of "
        f"{report.considered} production results looked at; "
        f"{answer['pass_to_fail']} pass→fail, {answer['fail_to_pass']} fail→pass, "
        f"{report.unchanged} unchanged, {report.failed} could not be replayed "
        f"({report.elapsed_s:.1f} s)"
    )
    console.print(Text(head), soft_wrap=True)
    if not report.complete:
        console.print(
            Text(f"stopped by the {report.stopped_by}: older images not replayed", style="yellow")
        )
    if report.rows_limited:
        console.print(Text("the row bound was reached: older results not looked at", "yellow"))
    if report.flipped:
        table = Table(header_style="bold")
        for column in ("result", "time", "stored", "new", "config", "current config"):
            table.add_column(column)
        for flip in report.flipped:
            table.add_row(
                str(flip.result_id),
                datetime.fromtimestamp(flip.time).isoformat(sep=" ", timespec="seconds"),
                _verdict(flip.stored),
                _verdict(flip.new),
                Text(flip.stored_config_hash[:12]),
                "yes" if flip.current_config else Text("no: stored under another", "yellow"),
            )
        console.print(table)
    for failure in report.errors:
        console.print(Text(f"result {failure.result_id}: {failure.code}: {failure.message}", "red"))


def _verdict(passed: bool) -> Text:
    return Text("PASS", style="green") if passed else Text("FAIL", style="bold red")
