"""The result log in PostgreSQL: one history for a plant's cells, with a local spool.

The durability promise is the SQLite log's (:mod:`.sqlite`): a result is acknowledged
with ``stored: true`` only once its row is safe. Here that means either

- **committed to PostgreSQL** (the normal case: :meth:`PgResultLog.record` inserts and commits
  before it returns the row's id), or
- **fsync'd to the local spool** (vision_server/results/spool.py) when the database cannot take
  it: down, unreachable, restarting, refusing connections. :meth:`~PgResultLog.record` then
  returns 0 (stored, id not known yet). A forwarder thread retries every ``retry_s`` and moves
  the spool to the database in batches, oldest first; while anything is spooled, new rows join
  the spool behind it (so that the database is never asked twice in a row to time out, and
  rows keep their order). The spool survives a restart of the server and is forwarded by the
  next one.

Each row carries a ``uid`` made here; the insert is ``ON CONFLICT (uid) DO NOTHING``, so a row
forwarded twice (the server died between the database's commit and the spool's delete, or a
commit whose answer was lost with the connection) is stored once.

A database that is down at start-up does not stop the server (the cell goes on inspecting into
the spool); one that answers but is not a result log, or has a newer schema, does
(:class:`ResultLogError`). Readers (the console, ``vision-server results``) read the database
and raise :class:`ResultLogError` while it is down. Images are not kept (``store_images:
none``): a plant database holds rows; the pictures stay on the cells' SQLite logs.
"""

from __future__ import annotations

import contextlib
import logging
import queue
import socket
import threading
import time
import uuid
from pathlib import Path
from types import TracebackType
from typing import Any
from urllib.parse import urlsplit, urlunsplit

import numpy as np

from .postgres_schema import SCHEMA_VERSION, check_version, migrate
from .query import COLUMNS, OPERATOR_COLUMNS, page_sql, timing_sql, where_sql
from .spool import Spool
from .store import (
    OperatorMark,
    ResultEntry,
    ResultLogError,
    StoredResult,
    TimingRows,
    is_row_id,
    parse_data,
    row_values,
)

__all__ = ["PgResultLog", "is_database_url", "redact_url"]

logger = logging.getLogger("vision_server.results")

_INSERT = (
    "INSERT INTO results (time, inspection, camera, passed, data, duration_ms, config_hash, "
    "request_id, peer, error, uid, cell, operator) "
    "VALUES (%s, %s, %s, %s, %s, %s, %s, %s, %s, %s, %s, %s, %s) ON CONFLICT (uid) DO NOTHING"
)
_UID = 10
"""Where a row's values (:func:`row_values`, then uid, cell and operator) have the uid."""
_VALUES = 13
"""Values a row has; a spool written by an older server has fewer (no operator): padded."""


def _padded(values: tuple[Any, ...]) -> tuple[Any, ...]:
    return values + (None,) * (_VALUES - len(values))


_BATCH = 500  # rows forwarded per transaction


def is_database_url(target: str | Path) -> bool:
    """Whether ``target`` names a PostgreSQL database rather than an SQLite file."""
    return isinstance(target, str) and target.startswith(("postgresql://", "postgres://"))


def redact_url(url: str) -> str:
    """``url`` without its password, for messages and logs."""
    parts = urlsplit(url)
    if parts.password is None:
        return url
    host = parts.hostname or ""
    netloc = f"{parts.username}:***@{host}" + (f":{parts.port}" if parts.port else "")
    return urlunsplit(parts._replace(netloc=netloc))


def _psycopg() -> Any:
    try:
        import psycopg
    except ImportError:
        raise ResultLogError(
            "a PostgreSQL result log needs psycopg: pip install 'cellvision[postgres]'"
        ) from None
    return psycopg


def _text(value: Any) -> Any:
    # PostgreSQL's text cannot hold NUL; a client's peer or error string might. A row the
    # database refuses would block the spool behind it, so the character is replaced.
    return value.replace("\x00", "\ufffd") if isinstance(value, str) else value


class PgResultLog:
    """The PostgreSQL result log. Thread-safe; use it as a context manager or call :meth:`close`.

    Parameters
    ----------
    url : str
        ``postgresql://user[:password]@host[:port]/database`` (libpq's URL form).
    spool : Path
        The local spool file (created when missing); required for writing.
    retry_s : float
        Seconds between the forwarder's attempts while rows are spooled.
    connect_timeout_s : float
        How long a connection attempt may take before the database counts as down.

    Raises
    ------
    ResultLogError
        psycopg is not installed, the spool cannot be opened, or the database answers but is
        not a result log or has a newer schema (a read-only view also when it is unreachable).
    """

    ids_in_commit_order = False
    """False: a sequence hands ids out before the rows commit, and many cells write, so a
    later commit may carry a smaller id (``ResultStore.ids_in_commit_order``)."""

    def __init__(
        self,
        url: str,
        *,
        spool: Path | None = None,
        retry_s: float = 1.0,
        connect_timeout_s: float = 5.0,
        _readonly: bool = False,
    ) -> None:
        self._pg = _psycopg()
        self.url = url
        self.where = redact_url(url)
        self.readonly = _readonly
        self.retry_s = retry_s
        self.connect_timeout_s = connect_timeout_s
        self.cell = socket.gethostname()
        self._closed = False
        self._stop = threading.Event()  # tells the forwarder to finish
        self._schema_ready = False
        self._stats = threading.Lock()  # never held during I/O: health() runs on the event loop
        self._recorded = 0
        self._failed = 0
        self._failing = False
        self._errors = 0
        self._streak = 0
        self._last_error: str | None = None
        self._last_error_time: float | None = None
        self._database_up = False
        self._read_lock = threading.Lock()
        self._read_conn: Any = None
        # Idle write connections: a worker takes one (or opens one) per row, so that workers
        # recording at once each wait for their own commit, not for one another's.
        self._idle: queue.SimpleQueue[Any] = queue.SimpleQueue()
        if _readonly:
            self._spool: Spool | None = None
            try:
                self._read_conn = self._open_connection(migrating=False)
            except self._pg.Error as exc:
                raise ResultLogError(f"cannot open the result log {self.where}: {exc}") from exc
            return
        if spool is None:
            raise ValueError("a PostgreSQL result log needs a spool file to write")
        self._spool = Spool(spool)
        self._spooled = self._spool.count()
        # While True, records go to the spool (the forwarder empties it, then clears this).
        self._mode_lock = threading.Lock()
        self._pending = self._spooled > 0
        try:
            self._idle.put(self._open_connection(migrating=True))
        except (self._pg.OperationalError, self._pg.InterfaceError) as exc:
            self._fault("the result database is unreachable; results are spooled", exc)
            self._pending = True
        except (self._pg.Error, ResultLogError) as exc:
            self._spool.close()
            raise ResultLogError(f"cannot open the result log {self.where}: {exc}") from exc
        self._wake = threading.Event()
        if self._pending:  # a spool left by the last run: forward it now, not after retry_s
            self._wake.set()
        self._forwarder = threading.Thread(
            target=self._forward_loop, name="result-forwarder", daemon=True
        )
        self._forwarder.start()

    @classmethod
    def open_readonly(cls, url: str) -> PgResultLog:
        """A read-only view (``vision-server results``): no spool, no forwarder, no migration;
        the database must be reachable and at this cellvision's schema version."""
        return cls(url, _readonly=True)

    # ------------------------------------------------------------------ connections

    def _open_connection(self, *, migrating: bool) -> Any:
        conn = self._pg.connect(
            self.url,
            autocommit=True,
            connect_timeout=max(1, round(self.connect_timeout_s)),
            application_name="cellvision",
            # A pulled cable or a dead host must fail the write (and send the row to the
            # spool) within seconds, not after TCP's default retries of ~15 minutes: data
            # unacknowledged for 10 s, or an idle connection whose keepalives go unanswered.
            tcp_user_timeout=10_000,
            keepalives=1,
            keepalives_idle=5,
            keepalives_interval=2,
            keepalives_count=3,
        )
        try:
            if migrating and not self._schema_ready:
                migrate(conn, self.where)
                self._schema_ready = True
            elif not migrating:
                version = check_version(conn, self.where)
                if version < SCHEMA_VERSION:
                    raise ResultLogError(
                        f"{self.where} has result-log schema version {version}; start the "
                        f"server on it once to create or upgrade it to {SCHEMA_VERSION}"
                    )
        except BaseException:
            with contextlib.suppress(Exception):
                conn.close()
            raise
        with self._stats:
            self._database_up = True
        return conn

    @staticmethod
    def _drop(conn: Any) -> None:
        if conn is not None:
            with contextlib.suppress(Exception):
                conn.close()

    # ------------------------------------------------------------------ writing

    @property
    def keeps_images(self) -> bool:
        """Never: the plant database keeps rows only (see the module doc)."""
        return False

    def record(self, entry: ResultEntry) -> int | None:
        """Store one result: its id once committed to the database, 0 once fsync'd to the
        spool (forwarded later), ``None`` when neither worked (the row is lost and counted).

        Never raises for runtime faults; raises :class:`ResultLogError` on a read-only view.
        """
        if self.readonly:
            raise ResultLogError(f"{self.where} was opened read-only: it cannot record results")
        try:
            if self._closed:
                raise ResultLogError("the result log is closed")
            values = (
                *(_text(v) for v in row_values(entry)),
                uuid.uuid4().hex,
                self.cell,
                _text(entry.operator) or None,
            )
        except Exception as exc:
            self._fault(f"result of {entry.inspection!r} not recorded", exc, row_lost=True)
            return None
        with self._mode_lock:
            direct = not self._pending
        if direct:
            row_id = self._insert_now(values)
            if row_id is not None:
                return row_id
        return self._spool_row(entry.inspection, values)

    def _insert_now(self, values: tuple[Any, ...]) -> int | None:
        """Insert and commit one row; None when the database cannot (it is then marked down)."""
        conn: Any = None
        try:
            with contextlib.suppress(queue.Empty):
                conn = self._idle.get_nowait()
            if conn is None or conn.closed:
                conn = self._open_connection(migrating=True)
            with conn.transaction():
                row = conn.execute(_INSERT + " RETURNING id", values).fetchone()
        except Exception as exc:
            # The commit's fate may be unknown (the connection died on COMMIT): the spool
            # takes the row, and its uid makes the second insert a no-op if it did commit.
            self._drop(conn)
            self._close_idle()  # they went through the same outage: reconnect afresh after it
            self._fault("the result database did not take a row; spooling", exc)
            return None
        self._idle.put(conn)
        if self._closed:  # close() may have emptied the queue before this put
            self._close_idle()
        self._wrote(1)
        return int(row[0]) if row is not None else 0

    def _close_idle(self) -> None:
        while True:
            try:
                self._drop(self._idle.get_nowait())
            except queue.Empty:
                return

    def _spool_row(self, inspection: str, values: tuple[Any, ...]) -> int | None:
        assert self._spool is not None
        with self._mode_lock:
            try:
                self._spool.add(values[_UID], values)
            except Exception as exc:
                self._fault(f"result of {inspection!r} not recorded", exc, row_lost=True)
                return None
            # Wake the forwarder when the spool starts, not per row: while the database is
            # down it retries every retry_s, not once per result.
            starting, self._pending = not self._pending, True
            with self._stats:
                self._spooled += 1
                self._failing = False
        if starting:
            self._wake.set()
        return 0

    def _wrote(self, rows: int) -> None:
        with self._stats:
            self._recorded += rows
            self._failing = False
            self._database_up = True
            streak, self._streak = self._streak, 0
        if streak:
            logger.warning("result database %s is back after %d faults", self.where, streak)

    # ------------------------------------------------------------------ forwarding

    def _forward_loop(self) -> None:
        conn: Any = None
        while not self._stop.is_set():
            self._wake.wait(self.retry_s)
            self._wake.clear()
            if self._stop.is_set():
                break
            with self._mode_lock:
                pending = self._pending
            if pending:
                conn = self._drain(conn)
        self._drop(conn)

    def _drain(self, conn: Any) -> Any:
        """Forward the spool until it is empty or the database fails; return the connection
        to reuse (None after a failure)."""
        assert self._spool is not None
        while not self._stop.is_set():
            batch = self._spool.take(_BATCH)
            try:
                # Connected even for an empty spool: spool mode ends only once the database
                # answered (a server that started while it was down has no schema there yet).
                if conn is None or conn.closed:
                    conn = self._open_connection(migrating=True)
                refused = 0
                if batch:
                    try:
                        with conn.transaction(), conn.cursor() as cur:
                            cur.executemany(_INSERT, [_padded(values) for _, values in batch])
                    except (self._pg.DataError, self._pg.IntegrityError):
                        refused = self._forward_singly(conn, batch)
            except Exception as exc:
                self._drop(conn)
                self._fault("forwarding the spool failed; retrying", exc)
                return None
            if not batch:
                with self._mode_lock:
                    done = self._spool.count() == 0
                    if done:
                        self._pending = False
                if done:
                    self._wrote(0)  # the database is back, with nothing left to forward
                    return conn
                continue
            try:
                self._spool.remove([uid for uid, _ in batch])
            except Exception as exc:
                # Forwarded but still spooled: the next pass inserts nothing (uid) and retries.
                self._fault("cannot remove forwarded rows from the spool", exc)
                return conn
            # Under the mode lock, as _spool_row counts: a health report that says 0 spooled
            # means new rows go to the database directly again.
            with self._mode_lock, self._stats:
                self._spooled -= len(batch)
                if self._spooled == 0:
                    self._pending = False
            self._wrote(len(batch) - refused)
        return conn

    def _forward_singly(self, conn: Any, batch: list[tuple[str, tuple[Any, ...]]]) -> int:
        """Forward a batch the database refused row by row; return how many rows it refuses.

        Only for a refusal of the rows themselves (a value it cannot store, a constraint of its
        own): such a row would block the spool behind it forever, so it is dropped, logged with
        its uid and counted as lost (health turns not ok). Anything else (the database down,
        permissions) raises, and the batch stays spooled.
        """
        refused = 0
        for uid, values in batch:
            try:
                with conn.transaction():
                    conn.execute(_INSERT, _padded(values))
            except (self._pg.DataError, self._pg.IntegrityError) as exc:
                refused += 1
                self._fault(
                    f"the database refuses spooled result {uid}; dropped", exc, row_lost=True
                )
        return refused

    def _fault(self, what: str, exc: BaseException, *, row_lost: bool = False) -> None:
        message = f"{what}: {str(exc).strip()}"
        with self._stats:
            if row_lost:
                self._failed += 1
                self._failing = True
            else:
                self._database_up = False
            self._errors += 1
            self._streak += 1
            first = self._streak == 1
            self._last_error = message
            self._last_error_time = time.time()
        log = logger.error if first or row_lost else logger.debug
        log("result log %s: %s", self.where, message)

    # ------------------------------------------------------------------ reading

    def _read(self, sql: str, params: tuple[Any, ...]) -> list[tuple[Any, ...]]:
        with self._read_lock:
            if self._closed:
                raise ResultLogError(f"the result log {self.where} is closed")
            try:
                if self._read_conn is None or self._read_conn.closed:
                    self._read_conn = self._open_connection(migrating=False)
                rows: list[tuple[Any, ...]] = self._read_conn.execute(sql, params).fetchall()
            except self._pg.Error as exc:
                self._drop(self._read_conn)
                self._read_conn = None
                raise ResultLogError(f"cannot read the result log {self.where}: {exc}") from exc
        return rows

    def query(
        self,
        *,
        since: float | None = None,
        inspection: str | None = None,
        passed: bool | None = None,
        limit: int = 100,
        newest_first: bool = True,
        peer: str | None = None,
        before_id: int | None = None,
        operator: str | None = None,
    ) -> list[StoredResult]:
        """As :meth:`vision_server.results.ResultLog.query`."""
        sql, params = self.query_sql(
            operator=operator,
            since=since,
            inspection=inspection,
            passed=passed,
            limit=limit,
            newest_first=newest_first,
            peer=peer,
            before_id=before_id,
        )
        return [_stored(row) for row in self._read(sql, params)]

    def query_sql(
        self,
        *,
        since: float | None = None,
        inspection: str | None = None,
        passed: bool | None = None,
        limit: int = 100,
        newest_first: bool = True,
        peer: str | None = None,
        before_id: int | None = None,
        operator: str | None = None,
    ) -> tuple[str, tuple[Any, ...]]:
        """The SQL and parameters :meth:`query` runs."""
        return page_sql(
            operator=operator,
            since=since,
            inspection=inspection,
            passed=passed,
            limit=limit,
            newest_first=newest_first,
            peer=peer,
            before_id=before_id,
            key_of=self._key_of,
            mark="%s",
            boolean=bool,
        )

    def _key_of(self, row_id: int) -> tuple[float, int] | None:
        rows = self._read("SELECT time, id FROM results WHERE id = %s", (row_id,))
        return (float(rows[0][0]), int(rows[0][1])) if rows else None

    def timings(
        self, *, inspection: str, since: float
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """As :meth:`vision_server.results.ResultLog.timings`."""
        rows = self.timing_rows(inspection=inspection, since=since)
        return rows.times, rows.passed, rows.durations

    def timing_rows(
        self, *, inspection: str, since: float | None = None, after_id: int | None = None
    ) -> TimingRows:
        """As :meth:`vision_server.results.ResultLog.timing_rows`."""
        upto = int(self._read("SELECT coalesce(max(id), 0) FROM results", ())[0][0])
        sql, params = timing_sql(
            inspection,
            since=since,
            after_id=after_id,
            upto_id=upto,
            mark="%s",
            boolean=bool,
            passed_column="passed::int",
        )
        return TimingRows.of(self._read(sql, params), upto)

    def count(
        self,
        *,
        since: float | None = None,
        inspection: str | None = None,
        passed: bool | None = None,
    ) -> int:
        """How many results match the filters (all of them without filters)."""
        where, params = where_sql(since, inspection, passed, mark="%s", boolean=bool)
        return int(self._read(f"SELECT count(*) FROM results{where}", params)[0][0])

    def get(self, row_id: int) -> StoredResult | None:
        """The result with id ``row_id``, or None."""
        if not is_row_id(row_id):
            return None
        rows = self._read(f"SELECT {COLUMNS} FROM results WHERE id = %s", (int(row_id),))
        return _stored(rows[0]) if rows else None

    def annotate(self, row_id: int, *, name: str, choice: str, reason: str, at: float) -> bool:
        """As :meth:`vision_server.results.ResultLog.annotate`: one UPDATE on a write
        connection. ResultLogError when the database cannot take it now (nothing is spooled:
        the answer itself reached the robot and the server's log)."""
        if not is_row_id(row_id):
            return False
        if self.readonly:
            raise ResultLogError(f"{self.where} was opened read-only: it cannot annotate results")
        self._check_open()
        conn: Any = None
        try:
            with contextlib.suppress(queue.Empty):
                conn = self._idle.get_nowait()
            if conn is None or conn.closed:
                conn = self._open_connection(migrating=True)
            with conn.transaction():
                cursor = conn.execute(
                    "UPDATE results SET operator = %s, operator_choice = %s, "
                    "operator_reason = %s, operator_at = %s WHERE id = %s",
                    (_text(name), choice, _text(reason) or None, float(at), int(row_id)),
                )
                done = bool(cursor.rowcount > 0)
        except Exception as exc:
            self._drop(conn)
            raise ResultLogError(f"cannot annotate result {row_id} in {self.where}: {exc}") from exc
        self._idle.put(conn)
        if self._closed:
            self._close_idle()
        return done

    def _check_open(self) -> None:
        if self._closed:
            raise ResultLogError(f"the result log {self.where} is closed")

    # ------------------------------------------------------------------ status and lifetime

    @property
    def errors(self) -> int:
        """Faults since the log was opened (a database outage counts once per failed try)."""
        return self._errors

    def health(self) -> dict[str, Any]:
        """The SQLite log's report (``ok`` false once a row was lost, sticky), plus
        ``spooled`` (rows waiting for the database) and ``database_up`` (whether the latest
        contact with it worked). A database outage alone loses nothing: ``ok`` stays true."""
        with self._stats:
            return {
                "ok": self._failed == 0,
                "written": self._recorded,
                "failed": self._failed,
                "failing": self._failing,
                "images_failed": 0,
                "last_error": self._last_error,
                "last_error_time": self._last_error_time,
                "spooled": 0 if self.readonly else self._spooled,
                "database_up": self._database_up,
            }

    def close(self) -> None:
        """Stop the forwarder (what is spooled stays for the next start) and disconnect."""
        if self._closed:
            return
        self._closed = True
        self._stop.set()
        if not self.readonly:
            self._wake.set()
            self._forwarder.join()
            assert self._spool is not None
            self._spool.close()
        self._close_idle()
        with self._read_lock:
            self._drop(self._read_conn)

    def __enter__(self) -> PgResultLog:
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        self.close()


def _stored(row: tuple[Any, ...]) -> StoredResult:
    (row_id, t, inspection, camera, passed, data, duration, chash, rid, peer, error) = row[:11]
    return StoredResult(
        id=int(row_id),
        time=float(t),
        inspection=inspection,
        camera=camera,
        passed=bool(passed),
        data=parse_data(data),
        duration_ms=float(duration),
        config_hash=chash,
        request_id=int(rid),
        peer=peer,
        error=error,
        image_path=None,
        overlay_path=None,
        operator=OperatorMark.from_columns(*row[OPERATOR_COLUMNS]),
    )
