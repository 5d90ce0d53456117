"""``vision-server results``: list the result log, as a table for people or JSON lines for tools.

The command opens the log read-only (:func:`vision_server.results.open_readonly`: an SQLite file
or a PostgreSQL URL), so it runs safely beside a server that is writing to it.
"""

from __future__ import annotations

import json
import math
import re
import time
from collections.abc import Mapping
from datetime import datetime
from pathlib import Path
from typing import Any

from rich.console import Console
from rich.markup import escape
from rich.table import Table
from rich.text import Text

from protocol.cli import ErrorKind, json_error

from ..results import ResultLogError, StoredResult, open_readonly, redact_url

__all__ = ["describe_health", "parse_since", "results_command"]

_UNITS = {"s": 1.0, "m": 60.0, "h": 3600.0, "d": 86400.0, "w": 7 * 86400.0}
_RELATIVE = re.compile(r"(?:\d+(?:\.\d+)?[smhdw])+")
_PART = re.compile(r"(\d+(?:\.\d+)?)([smhdw])")
_MEASURES_SHOWN = 3


def parse_since(text: str, *, now: float | None = None) -> float:
    """The Unix time that ``--since`` means.

    Accepts a duration back from ``now`` (``90s``, ``10m``, ``2h``, ``1d``, ``1w``, or combined:
    ``1h30m``) or an ISO 8601 date or date-time (``2024-05-01``, ``2024-05-01T08:30``,
    ``2024-05-01 08:30:00+02:00``); without a UTC offset it is local time.

    Raises
    ------
    ValueError
        ``text`` is neither; the message says what is accepted.
    """
    value = text.strip().lower()
    if _RELATIVE.fullmatch(value):
        seconds = sum(float(n) * _UNITS[unit] for n, unit in _PART.findall(value))
        return (time.time() if now is None else now) - seconds
    try:
        moment = datetime.fromisoformat(text.strip())
    except ValueError:
        raise ValueError(
            f"--since {text!r}: expected a duration such as 10m, 2h, 1d or 1h30m, or an ISO "
            "date/time such as 2024-05-01 or 2024-05-01T08:30"
        ) from None
    # A naive datetime is local time: .timestamp() interprets it so.
    return moment.timestamp()


def describe_health(health: Mapping[str, Any] | None) -> str:
    """One line for a PONG's health report (SPEC §5.5), for ``vision-server ping``.

    ``result log: 14 written, 286 failed (failing now); last error 2024-05-01 08:30:12: ...``
    """
    if health is None:
        return "the server sent no health report"
    return _result_log_text(health) + _mqtt_text(health.get("mqtt"))


def _mqtt_text(mqtt: Any) -> str:
    """``; MQTT to host:port connected, 3 spooled, 1042 published, 0 dropped`` (docs/mqtt.md)."""
    if not isinstance(mqtt, Mapping):
        return ""
    state = "connected" if mqtt.get("connected") else "NOT CONNECTED"
    text = (
        f"; MQTT to {mqtt.get('broker', '?')} {state}, {mqtt.get('spooled', '?')} spooled, "
        f"{mqtt.get('published', '?')} published, {mqtt.get('dropped', '?')} dropped"
    )
    if mqtt.get("spool_errors"):
        text += f", {mqtt['spool_errors']} not spooled"
    if mqtt.get("last_error"):
        text += f" ({mqtt['last_error']})"
    return text


def _result_log_text(health: Mapping[str, Any]) -> str:
    log = health.get("result_log")
    if not isinstance(log, Mapping):
        return "no result log" if health.get("ok") is True else "not ok"
    text = f"result log: {log.get('written', '?')} written, {log.get('failed', '?')} failed"
    if log.get("failing") is True:
        text += " (failing now)"
    elif log.get("ok") is False:
        text += " (writing again; restart the server to clear)"
    if log.get("images_failed"):
        text += f", {log['images_failed']} without their image"
    if "spooled" in log:  # a PostgreSQL log (vision_server/results/postgres.py)
        state = "up" if log.get("database_up") else "DOWN"
        text += f", {log['spooled']} spooled for the database ({state})"
    if log.get("last_error"):
        when = log.get("last_error_time")
        at = ""
        if isinstance(when, int | float) and math.isfinite(when):
            at = " " + datetime.fromtimestamp(when).isoformat(sep=" ", timespec="seconds")
        text += f"; last error{at}: {log['last_error']}"
    return text


def results_command(
    db: Path | str,
    *,
    since: str | None,
    inspection: str | None,
    json_out: bool,
    limit: int,
    failed_only: bool,
    console: Console,
    err_console: Console | None = None,
) -> int:
    """List results, newest first; return the exit status (0 ok; 2 a bad argument or no
    readable log: the table of docs/integrator-guide.md §6, where 1 means a fail verdict).

    ``json_out`` writes one JSON object per line (see :meth:`StoredResult.to_json`) to
    ``console.file`` and nothing else, and an error as the one JSON error shape; otherwise a
    table, and errors go to ``err_console`` (default: standard error).
    """
    err = err_console if err_console is not None else Console(stderr=True)

    def fail(message: str) -> int:
        if json_out:
            console.file.write(json.dumps(json_error(ErrorKind.USAGE, message)) + "\n")
            console.file.flush()
        else:
            err.print(f"[red]error:[/] {escape(message)}", highlight=False, soft_wrap=True)
        return int(ErrorKind.USAGE.exit_code)

    try:
        since_time = parse_since(since) if since is not None else None
    except ValueError as exc:
        return fail(str(exc))
    if limit < 0:
        return fail(f"--limit must be >= 0, got {limit}")
    passed = False if failed_only else None
    try:
        with open_readonly(db) as log:
            rows = log.query(since=since_time, inspection=inspection, passed=passed, limit=limit)
            total = log.count(since=since_time, inspection=inspection, passed=passed)
    except ResultLogError as exc:
        return fail(str(exc))
    if json_out:
        for row in rows:
            console.file.write(json.dumps(row.to_json(), separators=(",", ":")) + "\n")
        console.file.flush()
        return 0
    console.print(_table(rows, total, db))
    return 0


def _table(rows: list[StoredResult], total: int, db: Path | str) -> Table:
    where = redact_url(db) if isinstance(db, str) else str(db)
    table = Table(
        title=Text(f"Results in {where}"),
        caption=f"{len(rows)} of {total} matching, newest first",
        header_style="bold",
    )
    table.add_column("id", justify="right")
    table.add_column("time")
    table.add_column("inspection")
    table.add_column("camera")
    table.add_column("verdict")
    tries = any(row.is_try for row in rows)
    if tries:  # the column only when a console try is among the rows
        table.add_column("try")
    table.add_column("measures")
    table.add_column("ms", justify="right")
    table.add_column("image", overflow="fold")
    for row in rows:
        table.add_row(
            str(row.id),
            datetime.fromtimestamp(row.time).isoformat(sep=" ", timespec="seconds"),
            Text(row.inspection),
            Text(row.camera),
            _verdict(row),
            # A console try (its options are under "try" in the measures), not production.
            *([Text("try", style="yellow") if row.is_try else Text("")] if tries else []),
            Text(_summarise(row.data)),
            f"{row.duration_ms:.1f}",
            Text(str(row.image_path) if row.image_path is not None else ""),
        )
    return table


def _verdict(row: StoredResult) -> Text:
    if row.error is not None:
        return Text("ERROR", style="bold red")
    return Text("PASS", style="green") if row.passed else Text("FAIL", style="bold red")


def _summarise(data: dict[str, Any]) -> str:
    """The first few measures as ``key=value``; lists and objects by their size."""
    parts = [f"{key}={_short(value)}" for key, value in list(data.items())[:_MEASURES_SHOWN]]
    if len(data) > _MEASURES_SHOWN:
        parts.append(f"+{len(data) - _MEASURES_SHOWN}")
    return " ".join(parts)


def _short(value: Any) -> str:
    if isinstance(value, bool) or value is None:
        return str(value).lower()
    if isinstance(value, float):
        return f"{value:.4g}" if math.isfinite(value) else str(value)
    if isinstance(value, list):
        return f"[{len(value)}]"
    if isinstance(value, dict):
        return f"{{{len(value)}}}"
    text = str(value)
    return text if len(text) <= 24 else text[:23] + "…"
