"""The SQL of the result log's readers, written once for both databases.

SQLite marks parameters with ``?``, psycopg with ``%s``; everything else (row values, keyset
paging, the peer prefix as a range) is the same text, so that both logs answer a filter alike.
PostgreSQL's ``peer`` column uses the "C" collation for the same reason: the prefix range below
assumes text compares by code point, as SQLite's does.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Any

from .store import MAX_ROW_ID
from .tries import TRY_PEER_PREFIX

__all__ = ["COLUMNS", "OPERATOR_COLUMNS", "KeyLookup", "page_sql", "where_sql"]

COLUMNS = (
    "id, time, inspection, camera, passed, data, duration_ms, config_hash, request_id, peer, "
    "error, image, overlay, operator, operator_choice, operator_reason, operator_at"
)
OPERATOR_COLUMNS = slice(13, 17)
"""Where a row of :data:`COLUMNS` has its operator's name, choice, reason and time."""

KeyLookup = Callable[[int], "tuple[float, int] | None"]
"""The (time, id) of a row by id, or None when there is no such row."""


def where_sql(
    since: float | None,
    inspection: str | None,
    passed: bool | None,
    *,
    mark: str,
    boolean: Callable[[bool], Any],
    production: bool = False,
) -> tuple[str, tuple[Any, ...]]:
    """`` WHERE ...`` (or ``""``) and its parameters; ``boolean`` converts ``passed`` to the
    database's type (SQLite stores 0/1, PostgreSQL a boolean). ``production`` leaves out the
    console's tries (their peer prefix, as a range like the peer filter's)."""
    clauses: list[str] = []
    params: list[Any] = []
    if production:
        prefix = TRY_PEER_PREFIX
        clauses.append(f"NOT (peer >= {mark} AND peer < {mark})")
        params.extend((prefix, prefix[:-1] + chr(ord(prefix[-1]) + 1)))
    if since is not None:
        if not math.isfinite(since):
            raise ValueError(f"since must be a finite Unix time, got {since}")
        clauses.append(f"time >= {mark}")
        params.append(float(since))
    if inspection is not None:
        clauses.append(f"inspection = {mark}")
        params.append(inspection)
    if passed is not None:
        clauses.append(f"passed = {mark}")
        params.append(boolean(passed))
    return (" WHERE " + " AND ".join(clauses) if clauses else ""), tuple(params)


def timing_sql(
    inspection: str,
    *,
    since: float | None,
    after_id: int | None,
    upto_id: int,
    mark: str,
    boolean: Callable[[bool], Any],
    passed_column: str = "passed",
) -> tuple[str, tuple[Any, ...]]:
    """The id, time, verdict (0/1) and duration of ``inspection``'s production rows with
    ``time >= since`` (by time, through the covering index) or with ``id > after_id`` (by id,
    a range of the primary key: only the rows written since), never beyond row ``upto_id``."""
    where, params = where_sql(since, inspection, None, mark=mark, boolean=boolean, production=True)
    clauses = [where[len(" WHERE ") :]] if where else []
    extra: list[Any] = []
    if after_id is not None:
        clauses.append(f"id > {mark}")
        extra.append(int(after_id))
    clauses.append(f"id <= {mark}")
    extra.append(int(upto_id))
    order = "time" if after_id is None else "id"
    sql = (
        f"SELECT id, time, {passed_column}, duration_ms FROM results WHERE "
        + " AND ".join(clauses)
        + f" ORDER BY {order}"
    )
    return sql, params + tuple(extra)


def page_sql(
    *,
    since: float | None,
    inspection: str | None,
    passed: bool | None,
    limit: int,
    newest_first: bool,
    peer: str | None,
    before_id: int | None,
    key_of: KeyLookup,
    mark: str,
    boolean: Callable[[bool], Any],
    operator: str | None = None,
) -> tuple[str, tuple[Any, ...]]:
    """The query of one page of results (see :meth:`ResultStore.query` for the filters)."""
    if operator:
        # A person's rows are few among the log's: read them through the operator's index
        # and apply the other filters to them. Written so that no other index can serve
        # ``inspection`` or ``passed`` (an expression of a column hides it from the planner,
        # in both databases): an equality on their indexes ties with the operator's, and
        # could make a page read every row of an inspection for a few of one person's.
        where, params = where_sql(since, None, None, mark=mark, boolean=boolean)
        extra = [f"operator = {mark}"]
        params = (*params, operator)
        if inspection is not None:
            extra.append(f"inspection || '' = {mark}")
            params = (*params, inspection)
        if passed is not None:
            extra.append(f"(CASE WHEN passed THEN 1 ELSE 0 END) = {mark}")
            params = (*params, 1 if passed else 0)
    else:
        where, params = where_sql(since, inspection, passed, mark=mark, boolean=boolean)
        extra = []
    if peer:
        # A prefix as a range (an index can serve it, LIKE's wildcards play no part: a peer
        # may contain '_'); the upper bound is the prefix with its last character's
        # successor, and text compares by code point.
        extra.append(f"peer >= {mark}")
        params = (*params, peer)
        if ord(peer[-1]) < 0x10FFFF:
            extra.append(f"peer < {mark}")
            params = (*params, peer[:-1] + chr(ord(peer[-1]) + 1))
    if before_id is not None:
        # Keyset paging in the order shown: rows before (time, id) of row ``before_id``.
        # An id alone would skip or repeat rows whose time and id orders differ (workers
        # finish out of order), and would read every newer row to find its place. An id
        # that is not in the log (never written yet) falls back to the ids below it.
        cmp = "<" if newest_first else ">"
        # An id beyond any a row may have is past every row: the page from the newest.
        before_id = min(int(before_id), MAX_ROW_ID)
        key = key_of(before_id)
        if key is None:
            extra.append(f"id {cmp} {mark}")
            params = (*params, int(before_id))
        else:
            extra.append(f"(time, id) {cmp} ({mark}, {mark})")
            params = (*params, float(key[0]), int(key[1]))
    if extra:
        where = (where + " AND " if where else " WHERE ") + " AND ".join(extra)
    order = "DESC" if newest_first else "ASC"
    sql = f"SELECT {COLUMNS} FROM results{where} ORDER BY time {order}, id {order} LIMIT {mark}"
    return sql, (*params, max(0, int(limit)))
