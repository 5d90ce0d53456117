"""The result log as CSV: ``GET /api/results.csv`` (docs/console.md, "Results").

The same filters as ``GET /api/results``, newest first, streamed a page at a time through the
log's indexed query (a page costs about its rows whatever the log's size), so an export of
100,000 rows holds one page in memory, not the export. Text that a spreadsheet would read as a
formula (a cell starting ``=``, ``+``, ``-``, ``@``, a tab or a carriage return: a robot's peer
name or a code's payload is not trusted) is written with a leading apostrophe.
"""

from __future__ import annotations

import asyncio
import csv
import io
import json
import time
from collections.abc import Callable, Mapping
from datetime import UTC, datetime
from typing import Any

from aiohttp import web

from ..results import ResultStore, StoredResult
from .http_common import HttpError, float_param, int_param

PAGE_ROWS = 500
"""Rows read from the log per query while streaming."""
DEFAULT_ROWS = 10_000
MAX_ROWS = 1_000_000
"""The most rows one export may ask (``limit``)."""
MAX_EXPORTS = 2
"""Exports at once (a third is 503 BUSY): each holds a worker thread while it formats."""
COLUMNS = (
    "id",
    "time_iso",
    "time",
    "inspection",
    "camera",
    "verdict",
    "try",
    "duration_ms",
    "peer",
    "request_id",
    "config_hash",
    "error",
    "operator",
    "operator_choice",
    "operator_reason",
    "data",
)
_FORMULA_START = ("=", "+", "-", "@", "\t", "\r")


def filters(query: Mapping[str, str], user_name: Callable[[str], str] = str) -> dict[str, Any]:
    """The result-log query's keyword arguments from a request's query string (the filters
    ``GET /api/results`` and this export share: ``operator`` a user's name as the log keeps
    it, at most 64 characters, written as ``user_name`` gives it: a configured user's name
    whatever its case); 400 ``BAD_REQUEST`` naming a bad one."""
    verdict = query.get("verdict") or None
    if verdict not in (None, "pass", "fail"):
        raise HttpError(400, "BAD_REQUEST", "verdict must be 'pass' or 'fail'")
    operator = query.get("operator") or None
    if operator is not None and len(operator) > 64:
        raise HttpError(400, "BAD_REQUEST", "operator must be a name of at most 64 characters")
    return {
        "since": float_param(query, "since"),
        "inspection": query.get("inspection") or None,
        "passed": None if verdict is None else verdict == "pass",
        "peer": query.get("peer") or None,
        "operator": None if operator is None else user_name(operator),
    }


def row_cells(row: StoredResult) -> list[str]:
    """One result as the CSV's cells, in :data:`COLUMNS` order."""
    mark = row.operator
    cells: list[Any] = [
        row.id,
        datetime.fromtimestamp(row.time, UTC).isoformat(timespec="milliseconds"),
        f"{row.time:.3f}",
        row.inspection,
        row.camera,
        "pass" if row.passed else "fail",
        "1" if row.is_try else "0",
        f"{row.duration_ms:.3f}",
        row.peer,
        row.request_id,
        row.config_hash,
        row.error or "",
        mark.name if mark else "",
        (mark.choice or "") if mark else "",
        (mark.reason or "") if mark else "",
        json.dumps(row.data, separators=(",", ":"), ensure_ascii=False, default=str),
    ]
    return [_safe(str(cell)) for cell in cells]


def _safe(text: str) -> str:
    return "'" + text if text.startswith(_FORMULA_START) else text


class ExportRoutes:
    """``GET /api/results.csv`` over the log ``log()`` returns (it raises the console's 404
    when the server keeps none); ``user_name`` writes an operator filter's name as the log
    keeps it."""

    def __init__(
        self,
        log: Callable[[], ResultStore],
        user_name: Callable[[str], str] = str,
        headers: Mapping[str, str] | None = None,
    ) -> None:
        self.log = log
        self.user_name = user_name
        self.headers = dict(headers or {})
        """Sent with the CSV (the console's security headers: a streamed answer is sent
        before the middleware that adds them to other answers)."""
        self._running = 0

    def add_to(self, router: web.UrlDispatcher) -> None:
        router.add_get("/api/results.csv", self.export)

    async def export(self, request: web.Request) -> web.StreamResponse:
        query = request.query
        wanted = filters(query, self.user_name)
        limit = int_param(query, "limit", DEFAULT_ROWS, 1, MAX_ROWS)
        if self._running >= MAX_EXPORTS:
            raise HttpError(
                503, "BUSY", f"{self._running} exports are running; try again when one ends"
            )
        log = self.log()
        self._running += 1
        try:
            return await self._stream(request, log, wanted, limit)
        finally:
            self._running -= 1

    async def _stream(
        self, request: web.Request, log: ResultStore, wanted: dict[str, Any], limit: int
    ) -> web.StreamResponse:
        def page(before: int | None, rows_left: int) -> tuple[bytes, int | None, int]:
            """One page read and written as CSV in a worker thread (formatting 500 rows is
            milliseconds of Python: never on the event loop every robot's answer needs)."""
            rows = log.query(limit=min(PAGE_ROWS, rows_left), before_id=before, **wanted)
            last = rows[-1].id if len(rows) == min(PAGE_ROWS, rows_left) else None
            return _lines(row_cells(r) for r in rows), last, len(rows)

        # The first page is read before the answer starts, so that a log that cannot be read
        # is a JSON error (503), not a CSV cut short.
        data, last, sent = await asyncio.to_thread(page, None, limit)
        stamp = time.strftime("%Y%m%dT%H%M%S")
        response = web.StreamResponse(
            headers={
                **self.headers,
                "Content-Type": "text/csv; charset=utf-8",
                "Content-Disposition": f'attachment; filename="cellvision-results-{stamp}.csv"',
                "Cache-Control": "no-store",
            }
        )
        await response.prepare(request)
        await response.write(_lines([list(COLUMNS)]) + data)
        while last is not None and sent < limit:
            data, last, count = await asyncio.to_thread(page, last, limit - sent)
            sent += count
            await response.write(data)
        await response.write_eof()
        return response


def _lines(rows: Any) -> bytes:
    out = io.StringIO()
    writer = csv.writer(out, lineterminator="\r\n")
    writer.writerows(rows)
    return out.getvalue().encode("utf-8")


__all__ = ["COLUMNS", "ExportRoutes", "filters", "row_cells"]
