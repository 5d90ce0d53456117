"""The PostgreSQL result log's local spool: rows waiting for the database, on the cell's disk.

A small SQLite file in WAL mode with ``synchronous=FULL``: :meth:`Spool.add` returns only after
the row is fsync'd, so a result acknowledged from the spool survives a crash of the server and a
power loss alike (unlike the SQLite log's NORMAL, see :mod:`.sqlite`: the spool is the
only copy of a row, and it is written only while the database is down, so the fsync's cost is
paid rarely). Rows are keyed by their ``uid`` and leave the spool only after the database
committed them (:meth:`Spool.remove`), so a crash in between forwards them again: the database's
unique ``uid`` makes that second insert a no-op.
"""

from __future__ import annotations

import contextlib
import json
import sqlite3
import threading
from pathlib import Path
from typing import Any

from .store import ResultLogError

__all__ = ["Spool"]

_SCHEMA = """
CREATE TABLE IF NOT EXISTS spool (
    seq    INTEGER PRIMARY KEY AUTOINCREMENT,  -- forwarding order: the order of recording
    uid    TEXT NOT NULL UNIQUE,
    row    TEXT NOT NULL                        -- JSON array: the result's column values
)
"""


class Spool:
    """Rows keyed by uid, in the order added. Thread-safe.

    Raises
    ------
    ResultLogError
        The file cannot be created or opened (naming it and the cause).
    """

    def __init__(self, path: Path) -> None:
        self.path = Path(path)
        self._lock = threading.Lock()
        try:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            self._conn = sqlite3.connect(
                str(self.path), isolation_level=None, check_same_thread=False, timeout=5.0
            )
            mode = self._conn.execute("PRAGMA journal_mode = WAL").fetchone()[0]
            if str(mode).lower() != "wal":
                raise ResultLogError(f"{self.path}: cannot switch to WAL (journal mode {mode})")
            self._conn.execute("PRAGMA synchronous = FULL")
            self._conn.execute(_SCHEMA)
        except (sqlite3.Error, OSError) as exc:
            raise ResultLogError(f"cannot open the result spool {self.path}: {exc}") from exc

    def add(self, uid: str, row: tuple[Any, ...]) -> None:
        """Keep one row; returns once it is on disk. Raises ``sqlite3.Error`` or ``OSError``."""
        text = json.dumps(list(row), separators=(",", ":"))
        with self._lock:
            self._conn.execute("INSERT INTO spool (uid, row) VALUES (?, ?)", (uid, text))

    def take(self, limit: int) -> list[tuple[str, tuple[Any, ...]]]:
        """The oldest ``limit`` rows as (uid, row), left in the spool."""
        with self._lock:
            rows = self._conn.execute(
                "SELECT uid, row FROM spool ORDER BY seq LIMIT ?", (limit,)
            ).fetchall()
        return [(uid, tuple(json.loads(text))) for uid, text in rows]

    def remove(self, uids: list[str]) -> None:
        """Drop rows the database has committed."""
        with self._lock:
            self._conn.execute("BEGIN IMMEDIATE")
            try:
                self._conn.executemany("DELETE FROM spool WHERE uid = ?", [(u,) for u in uids])
                self._conn.execute("COMMIT")
            except BaseException:
                with contextlib.suppress(sqlite3.Error):
                    self._conn.execute("ROLLBACK")
                raise

    def count(self) -> int:
        with self._lock:
            return int(self._conn.execute("SELECT count(*) FROM spool").fetchone()[0])

    def close(self) -> None:
        with self._lock, contextlib.suppress(sqlite3.Error):
            self._conn.close()
