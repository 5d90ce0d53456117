"""The MQTT publisher's outbox: results waiting for the broker's PUBACK, on the cell's disk.

A small SQLite file in WAL mode with ``synchronous=NORMAL`` (the house style of
:mod:`vision_server.results.spool`, with the result log's durability rather than the PostgreSQL
spool's FULL: every result passes through this file, on the event loop, so no fsync per row).
A row is written before the front-end sends the RESULT it belongs to, so a result whose answer
reached a client is in the file: it survives a crash of the server process (a power loss may
take the last moments' rows, as it takes the result log's). Rows leave only when the broker
acknowledged them (:meth:`Outbox.remove`), or when the outbox is over its bound
(``spool_max_mb``): then the OLDEST rows are dropped and counted (:attr:`Outbox.dropped`).

The bound counts each row's topic and payload bytes plus :data:`ROW_OVERHEAD`; the file holds
that and SQLite's own pages (freed pages are reused, not returned to the disk) and its WAL
(checkpointed at about 4 MB).

``seq`` is the row's key and the payload's ``seq``: one more than the last ever given by this
file (SQLite's AUTOINCREMENT remembers it when the outbox is empty), so it increases over
restarts as long as the file is kept.
"""

from __future__ import annotations

import contextlib
import sqlite3
import threading
from dataclasses import dataclass
from pathlib import Path

from ...process import Claimed, claim

FORMAT = 1
"""``PRAGMA user_version`` of an outbox file: another value is not ours (or is newer)."""
MAX_UNDELETED = 100_000
"""Acknowledged rows kept in memory while the disk cannot delete them (a few MB at most)."""
ROW_OVERHEAD = 64
"""Bytes counted per row besides its topic and payload (key, uid, SQLite's record)."""

_SCHEMA = """
CREATE TABLE IF NOT EXISTS outbox (
    seq     INTEGER PRIMARY KEY AUTOINCREMENT,  -- publication order, the payload's seq
    uid     TEXT NOT NULL,
    topic   TEXT NOT NULL,
    payload BLOB NOT NULL,
    size    INTEGER NOT NULL                    -- bytes counted against the bound
)
"""


class OutboxError(Exception):
    """The outbox file cannot be opened or written (the message names it and the cause)."""


@dataclass(frozen=True)
class OutboxRow:
    seq: int
    uid: str
    topic: str
    payload: bytes


class Outbox:
    """Rows in publication order, bounded by ``max_bytes``. Thread-safe.

    Raises
    ------
    OutboxError
        The file cannot be created, is not an SQLite database (corrupt), fails SQLite's
        quick check, is another program's, or cannot be written.
    """

    def __init__(self, path: Path, max_bytes: int) -> None:
        self.path = Path(path)
        self.max_bytes = max_bytes
        self.dropped = 0
        """Rows dropped over the bound since this outbox was opened."""
        self._lock = threading.Lock()
        self._undeleted: set[int] = set()
        """Acknowledged rows the disk could not delete yet (see :meth:`remove`)."""
        self.delete_errors = 0
        """Deletes of acknowledged rows that failed (a full disk) since this outbox opened."""
        try:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            self._claim = claim(self.path, "the MQTT spool")
        except Claimed as exc:
            raise OutboxError(str(exc)) from None
        except OSError as exc:
            raise OutboxError(f"cannot open the MQTT spool {self.path}: {exc}") from exc
        try:
            self._conn = sqlite3.connect(
                str(self.path), isolation_level=None, check_same_thread=False, timeout=5.0
            )
        except (sqlite3.Error, OSError) as exc:
            self._claim.release()
            raise OutboxError(f"cannot open the MQTT spool {self.path}: {exc}") from exc
        try:
            self._open()
        except (sqlite3.Error, OSError) as exc:
            self._conn.close()
            self._claim.release()
            raise OutboxError(
                f"cannot use the MQTT spool {self.path}: {exc} (move the file away to start "
                "with an empty spool; its unsent results are then lost)"
            ) from exc
        except OutboxError:
            self._conn.close()
            self._claim.release()
            raise

    def _open(self) -> None:
        conn = self._conn
        version = int(conn.execute("PRAGMA user_version").fetchone()[0])
        if version not in (0, FORMAT):
            raise OutboxError(
                f"{self.path} is not a cellvision MQTT spool of format {FORMAT} "
                f"(user_version {version})"
            )
        check = conn.execute("PRAGMA quick_check").fetchone()[0]
        if str(check).lower() != "ok":
            raise OutboxError(f"the MQTT spool {self.path} is corrupt: {check}")
        mode = conn.execute("PRAGMA journal_mode = WAL").fetchone()[0]
        if str(mode).lower() != "wal":
            raise OutboxError(f"{self.path}: cannot switch to WAL (journal mode {mode})")
        conn.execute("PRAGMA synchronous = NORMAL")
        conn.execute(_SCHEMA)
        conn.execute(f"PRAGMA user_version = {FORMAT}")  # also proves the file writable
        last = conn.execute("SELECT seq FROM sqlite_sequence WHERE name = 'outbox'").fetchone()
        self._last_seq = int(last[0]) if last else 0
        rows, size = conn.execute("SELECT count(*), coalesce(sum(size), 0) FROM outbox").fetchone()
        self._rows = int(rows)
        self._bytes = int(size)

    # ------------------------------------------------------------------ writing

    def next_seq(self) -> int:
        """The seq the next :meth:`add` must use (read it and add under one caller)."""
        with self._lock:
            return self._last_seq + 1

    def add(self, row: OutboxRow) -> int:
        """Keep ``row`` (its seq from :meth:`next_seq`); returns how many of the oldest rows
        were dropped to stay within the bound (the newest row is always kept). Raises
        :class:`OutboxError` (a full disk)."""
        size = len(row.topic.encode("utf-8")) + len(row.payload) + ROW_OVERHEAD
        with self._lock:
            if row.seq <= self._last_seq:
                raise ValueError(f"seq {row.seq} is not after {self._last_seq}")
            try:
                self._conn.execute(
                    "INSERT INTO outbox (seq, uid, topic, payload, size) VALUES (?, ?, ?, ?, ?)",
                    (row.seq, row.uid, row.topic, row.payload, size),
                )
            except (sqlite3.Error, OSError) as exc:
                raise OutboxError(f"cannot write to the MQTT spool {self.path}: {exc}") from exc
            self._last_seq = row.seq
            self._rows += 1
            self._bytes += size
            try:
                return self._drop_over_bound()
            except (sqlite3.Error, OSError) as exc:
                raise OutboxError(f"cannot trim the MQTT spool {self.path}: {exc}") from exc

    def _drop_over_bound(self) -> int:
        dropped = 0
        while self._bytes > self.max_bytes and self._rows > 1:
            excess = self._bytes - self.max_bytes
            oldest = self._conn.execute(
                "SELECT seq, size FROM outbox ORDER BY seq LIMIT ?", (min(self._rows - 1, 1000),)
            ).fetchall()
            freed = count = last = 0
            for seq, size in oldest:
                if freed >= excess:
                    break
                freed += int(size)
                count += 1
                last = int(seq)
            self._conn.execute("DELETE FROM outbox WHERE seq <= ?", (last,))
            self._rows -= count
            self._bytes -= freed
            dropped += count
        self.dropped += dropped
        return dropped

    def remove(self, seq: int) -> bool:
        """Forget an acknowledged row; False when it was gone already (dropped).

        A row the disk cannot delete now (SQLite needs room in its log even to delete: a full
        disk) is remembered as acknowledged, skipped by :meth:`after` and deleted by a later
        call: otherwise every reconnect would send it again, for ever. Raises
        :class:`OutboxError` only when :data:`MAX_UNDELETED` such rows wait."""
        with self._lock:
            try:
                self._delete_acknowledged()
                gone = self._conn.execute(
                    "DELETE FROM outbox WHERE seq = ? RETURNING size", (seq,)
                ).fetchone()
            except (sqlite3.Error, OSError) as exc:
                if len(self._undeleted) >= MAX_UNDELETED:
                    raise OutboxError(
                        f"cannot delete from the MQTT spool {self.path}: {exc}"
                    ) from exc
                self._undeleted.add(seq)
                self.delete_errors += 1
                return True
            if gone is None:
                return False
            self._rows -= 1
            self._bytes -= int(gone[0])
            return True

    def _delete_acknowledged(self) -> None:
        """Delete the acknowledged rows an earlier :meth:`remove` could not (lock held)."""
        while self._undeleted:
            some = sorted(self._undeleted)[:500]
            marks = ",".join("?" * len(some))
            gone = self._conn.execute(
                f"DELETE FROM outbox WHERE seq IN ({marks}) RETURNING size",  # noqa: S608
                some,
            ).fetchall()
            self._rows -= len(gone)
            self._bytes -= sum(int(g[0]) for g in gone)
            self._undeleted.difference_update(some)

    # ------------------------------------------------------------------ reading

    def after(self, seq: int, limit: int) -> list[OutboxRow]:
        """The oldest ``limit`` rows with a seq above ``seq``, left in the outbox. Raises
        :class:`OutboxError`."""
        with self._lock:
            try:
                found = self._conn.execute(
                    "SELECT seq, uid, topic, payload FROM outbox WHERE seq > ? ORDER BY seq "
                    "LIMIT ?",
                    (seq, limit + len(self._undeleted)),
                ).fetchall()
            except (sqlite3.Error, OSError) as exc:
                raise OutboxError(f"cannot read the MQTT spool {self.path}: {exc}") from exc
            rows = [
                OutboxRow(int(s), str(u), str(t), bytes(p))
                for s, u, t, p in found
                if int(s) not in self._undeleted  # acknowledged already
            ]
        return rows[:limit]

    @property
    def rows(self) -> int:
        """Rows waiting (sent or not, not yet acknowledged)."""
        return self._rows

    @property
    def bytes(self) -> int:
        """Their bytes as the bound counts them."""
        return self._bytes

    def close(self) -> None:
        with self._lock, contextlib.suppress(sqlite3.Error):
            self._conn.close()
        self._claim.release()
