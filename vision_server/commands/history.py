"""``vision-server history``: the configuration file's versions (docs/console.md, "History"),
read-only and without a server.

    vision-server history --config cell.yaml [list] [--limit N] [--json]
    vision-server history --config cell.yaml show V     # version V's text, byte for byte
                                                        # (--json: its metadata and text)
    vision-server history --config cell.yaml diff V     # its changes from the version before

Exit codes: 0 ok, 2 usage (no --config, no such version, a history that cannot be read).
"""

from __future__ import annotations

import argparse
import json
import os
import sys
from datetime import datetime
from pathlib import Path
from typing import Any

from rich.console import Console
from rich.table import Table
from rich.text import Text

from protocol.cli import CONFIG_ENV, ErrorKind, json_error

from ..config import history

__all__ = ["add_parser", "history_command"]

KIND_TEXT = {
    history.SAVE: "save",
    history.REVERT: "revert to {reverted_to}",
    history.CREATED_INSPECTION: "new inspection",
    history.EDITED_OUTSIDE: "edited outside the console",
    history.ORIGINAL: "the file as found",
}


def add_parser(sub: Any, parents: list[argparse.ArgumentParser]) -> None:
    p = sub.add_parser(
        "history",
        parents=parents,
        help="list, show or diff the configuration file's versions (read-only)",
        description="The versions the console recorded in CONFIG.history/ beside the "
        "configuration file: who, when, why and which inspections changed. Read-only: no "
        "server needed, nothing written.",
    )
    p.add_argument(
        "action",
        nargs="?",
        choices=("list", "show", "diff"),
        default="list",
        help="list (default): versions newest first; show V: its text; diff V: its changes",
    )
    p.add_argument("version", nargs="?", type=_version, help="the version (show, diff)")
    p.add_argument("--limit", type=_version, default=50, help="versions listed (default 50)")
    p.set_defaults(func=history_command)


def _version(text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a version number, got {text!r}") from None
    if value < 1:
        raise argparse.ArgumentTypeError(f"versions are numbered from 1, got {value}")
    return value


def _fail(args: argparse.Namespace, message: str) -> int:
    if getattr(args, "json", False):
        print(json.dumps(json_error(ErrorKind.USAGE, message)))
    else:
        print(f"vision-server history: {message}", file=sys.stderr, flush=True)
    return int(ErrorKind.USAGE.exit_code)


def history_command(args: argparse.Namespace) -> int:
    config = getattr(args, "config", None) or os.environ.get(CONFIG_ENV) or None
    if not config:
        return _fail(args, f"give --config FILE (or ${CONFIG_ENV})")
    versions = history.History(Path(config))
    if not versions.config.exists() and not versions.folder.exists():
        return _fail(args, f"no such file: {config}")
    if args.action in ("show", "diff") and args.version is None:
        return _fail(args, f"{args.action} needs a version: history {args.action} V")
    try:
        if args.action == "list":
            return _list(args, versions)
        if args.action == "show" and args.json:
            version = versions.get(args.version)
            text = versions.text(args.version).decode("utf-8", "replace")
            print(json.dumps({**version.json(), "text": text}))
            return 0
        if args.action == "show":
            sys.stdout.flush()
            sys.stdout.buffer.write(versions.text(args.version))
            sys.stdout.buffer.flush()
            return 0
        if args.json:
            version = versions.get(args.version)
            print(json.dumps({**version.json(), "diff": versions.diff(args.version)}))
        else:
            sys.stdout.write(versions.diff(args.version))
        return 0
    except history.UnknownVersion as exc:
        return _fail(args, f"{exc} (in {versions.folder})")
    except OSError as exc:
        return _fail(args, f"cannot read the history {versions.folder}: {exc}")


def _list(args: argparse.Namespace, versions: history.History) -> int:
    page = versions.versions(limit=args.limit)
    if args.json:
        for version in page:
            print(json.dumps(version.json()))
        return 0
    if not page:
        print(
            f"{versions.config}: no versions yet ({versions.folder.name} is made by the "
            "console's first save)",
            file=sys.stderr,
        )
        return 0
    table = Table(title=Text(f"{versions.config}: versions, newest first"))
    for column in ("version", "time", "who", "what", "inspections", "why"):
        table.add_column(column)
    for version in page:
        what = KIND_TEXT.get(version.kind, version.kind).format(reverted_to=version.reverted_to)
        changed = ", ".join(version.inspections) if version.parsed else "(does not parse)"
        when = datetime.fromtimestamp(version.time).strftime("%Y-%m-%d %H:%M:%S")
        cells = (str(version.number), when, version.who, what, changed or "-", version.why)
        table.add_row(*map(Text, cells))
    width = None if sys.stdout.isatty() else 200
    Console(width=width).print(table)
    return 0
