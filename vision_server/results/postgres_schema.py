"""The PostgreSQL result log's schema and its versioned migrations.

The same table as the SQLite log (:mod:`.sqlite`), with PostgreSQL's types, plus what a
plant-wide history needs: ``uid``, a unique id per result made by the cell that recorded it, so
that forwarding a spooled row twice (a crash between the database's commit and the spool's
delete) inserts it once; and ``cell``, the host that recorded it.

``schema_version`` holds one row, the number of migrations applied. Each entry of
:data:`MIGRATIONS` upgrades version i to i + 1: append, never edit. Many cells may start at once
against one database: the upgrade runs in one transaction under an advisory lock, so one of them
migrates and the others find the work done.
"""

from __future__ import annotations

from typing import Any

from .store import ResultLogError

__all__ = ["MIGRATIONS", "SCHEMA_VERSION", "check_version", "migrate", "schema_version"]

MIGRATIONS: tuple[str, ...] = (
    """
    CREATE TABLE results (
        id          BIGINT GENERATED ALWAYS AS IDENTITY PRIMARY KEY,
        time        DOUBLE PRECISION NOT NULL,  -- Unix seconds
        inspection  TEXT    NOT NULL,
        camera      TEXT    NOT NULL,
        passed      BOOLEAN NOT NULL,
        data        TEXT    NOT NULL,           -- JSON object (NaN allowed: not jsonb)
        duration_ms DOUBLE PRECISION NOT NULL,
        config_hash TEXT    NOT NULL,
        request_id  BIGINT  NOT NULL DEFAULT 0,
        -- "C": the console's peer filter is a code-point range (vision_server/results/query.py)
        peer        TEXT COLLATE "C" NOT NULL DEFAULT '',
        error       TEXT,
        image       TEXT,
        image_bytes BIGINT  NOT NULL DEFAULT 0
    );
    CREATE INDEX results_by_time ON results (time);
    CREATE INDEX results_by_inspection ON results (inspection, time);
    CREATE TABLE meta (key TEXT PRIMARY KEY, value TEXT NOT NULL);
    """,
    """
    ALTER TABLE results ADD COLUMN overlay TEXT;
    -- Made by the recording cell; NULL for rows of version 1 (unique allows many NULLs).
    ALTER TABLE results ADD COLUMN uid TEXT;
    CREATE UNIQUE INDEX results_by_uid ON results (uid);
    ALTER TABLE results ADD COLUMN cell TEXT NOT NULL DEFAULT '';
    -- The console's filters read newest first (ORDER BY time DESC, id DESC).
    DROP INDEX results_by_inspection;
    CREATE INDEX results_by_inspection ON results (inspection, time, id);
    CREATE INDEX results_by_verdict ON results (passed, time, id);
    CREATE INDEX results_by_peer ON results (peer, time);
    """,
    """
    -- Who: a console try's user, or the operator who answered the call about this failed
    -- result, with their choice, reason and time (Unix seconds). NULL: nobody.
    ALTER TABLE results ADD COLUMN operator TEXT;
    ALTER TABLE results ADD COLUMN operator_choice TEXT;
    ALTER TABLE results ADD COLUMN operator_reason TEXT;
    ALTER TABLE results ADD COLUMN operator_at DOUBLE PRECISION;
    CREATE INDEX results_by_operator ON results (operator, time, id);
    """,
)
SCHEMA_VERSION = len(MIGRATIONS)

# pg_advisory_xact_lock's key: any constant that other applications of the database do not use.
_LOCK_KEY = 0x63656C6C76697331  # "cellvis1"


def schema_version(conn: Any) -> int | None:
    """The database's version, or None when it has no ``schema_version`` table.

    ``conn`` is a psycopg connection (typed loosely: psycopg is an optional dependency).
    """
    found = conn.execute("SELECT to_regclass('schema_version') IS NOT NULL").fetchone()[0]
    if not found:
        return None
    row = conn.execute("SELECT version FROM schema_version").fetchone()
    return 0 if row is None else int(row[0])


def check_version(conn: Any, where: str) -> int:
    """The version, refusing a newer one and a database that holds another application's
    ``results`` table."""
    version = schema_version(conn)
    if version is None:
        if conn.execute("SELECT to_regclass('results') IS NOT NULL").fetchone()[0]:
            raise ResultLogError(f"{where} has a results table but is not a cellvision result log")
        return 0
    if version > SCHEMA_VERSION:
        raise ResultLogError(
            f"{where} has result-log schema version {version}, newer than this cellvision's "
            f"{SCHEMA_VERSION}: upgrade cellvision to use it"
        )
    return version


def migrate(conn: Any, where: str, *, target: int = SCHEMA_VERSION) -> int:
    """Bring the database up to ``target`` (tests stop at older versions); return the version
    found. ``conn`` must be in autocommit mode: the upgrade is its own transaction."""
    with conn.transaction():
        conn.execute("SELECT pg_advisory_xact_lock(%s)", (_LOCK_KEY,))
        found = check_version(conn, where)
        if found < target:
            conn.execute("CREATE TABLE IF NOT EXISTS schema_version (version INTEGER NOT NULL)")
            for script in MIGRATIONS[found:target]:
                conn.execute(script)
            conn.execute("DELETE FROM schema_version")
            conn.execute("INSERT INTO schema_version (version) VALUES (%s)", (target,))
    return found
