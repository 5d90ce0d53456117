"""Results annotated by operator in the PostgreSQL result log, against a real, private cluster
(tests/helpers/postgres.py): an answer written onto a row, a try's user kept (also through the
spool, and from a spool written before the operator column existed), the filter by operator,
and a database of the previous schema version migrated in place."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from loopback import run, wait_until

from vision_server.results import PgResultLog, ResultEntry
from vision_server.results.postgres_schema import SCHEMA_VERSION, migrate, schema_version
from vision_server.results.spool import Spool

psycopg = pytest.importorskip(
    "psycopg", reason="psycopg is not installed: pip install -e '.[test]' (extra postgres)"
)

T0 = 1_700_000_000.0


def entry(i: int, **kw: object) -> ResultEntry:
    fields: dict[str, object] = {
        "time": T0 + i,
        "inspection": ("gap", "magnet_check")[i % 2],
        "camera": "qc",
        "passed": i % 3 != 0,
        "data": {"value": float(i)},
        "duration_ms": 1.0,
        "config_hash": "abc",
        "request_id": i,
        "peer": f"10.0.0.7:{40000 + i}",
    }
    fields.update(kw)
    return ResultEntry(**fields)  # type: ignore[arg-type]


def test_an_answer_and_a_try_user_are_kept_and_filtered(pg_url: str, tmp_path: Path) -> None:
    with PgResultLog(pg_url, spool=tmp_path / "spool.sqlite3", retry_s=0.05) as log:
        ids = [log.record(entry(i)) for i in range(10)]
        assert all(isinstance(i, int) and i > 0 for i in ids)
        try_id = log.record(entry(10, peer="console 127.0.0.1:5000", operator="ben"))
        assert try_id
        assert log.annotate(ids[4], name="anna", choice="continue", reason="cosmetic", at=T0 + 50)
        assert log.annotate(ids[8], name="anna", choice="abort", reason="", at=T0 + 60)
        assert not log.annotate(10**9, name="anna", choice="retry", reason="", at=T0)
        rows = log.query(operator="anna")
        assert [r.id for r in rows] == [ids[8], ids[4]]
        assert rows[1].operator is not None
        assert rows[1].operator.to_json() == {
            "name": "anna",
            "choice": "continue",
            "reason": "cosmetic",
            "at": T0 + 50,
        }
        assert rows[0].operator is not None
        assert rows[0].operator.reason is None
        assert [r.id for r in log.query(operator="anna", inspection="gap")] == [ids[8], ids[4]]
        assert [r.id for r in log.query(operator="anna", passed=False)] == []
        assert [r.id for r in log.query(operator="anna", before_id=ids[8])] == [ids[4]]
        (tried,) = log.query(operator="ben")
        assert tried.id == try_id
        assert tried.is_try
        assert tried.operator is not None
        assert tried.operator.choice is None
        assert log.get(ids[0]).operator is None  # type: ignore[union-attr]
        sql, params = log.query_sql(operator="anna", inspection="gap", limit=50)
        with psycopg.connect(pg_url) as conn:
            conn.execute("SET enable_seqscan = off")
            plan = " ".join(r[0] for r in conn.execute("EXPLAIN " + sql, params).fetchall())
        assert "results_by_operator" in plan, plan


def test_a_spool_of_an_older_server_is_forwarded(pg_url: str, tmp_path: Path) -> None:
    """Rows spooled by a server without the operator column (12 values) still go in."""
    spool_path = tmp_path / "spool.sqlite3"
    with PgResultLog(pg_url, spool=spool_path, retry_s=0.05):
        pass  # the schema exists
    spool = Spool(spool_path)
    old_row = (T0, "gap", "qc", False, json.dumps({"v": 1}), 1.0, "h", 3, "p", None, "u" * 32, "c")
    spool.add("u" * 32, old_row)
    spool.close()
    with PgResultLog(pg_url, spool=spool_path, retry_s=0.05) as log:
        run(wait_until(lambda: log.health()["spooled"] == 0 and log.count() == 1, "the old row"))
        (row,) = log.query()
        assert row.data == {"v": 1}
        assert row.operator is None
        # A try spooled by this server keeps its user once forwarded.
        values_spooled = log._spool_row(  # the path a row takes while the database is down
            "gap",
            (T0 + 1, "gap", "qc", True, "{}", 1.0, "h", 4, "console x", None, "v" * 32, "c", "ben"),
        )
        assert values_spooled == 0
        log._wake.set()
        run(wait_until(lambda: log.count() == 2, "the try forwarded"))
        assert [r.operator.name for r in log.query(operator="ben")] == ["ben"]  # type: ignore[union-attr]


def test_the_previous_schema_is_upgraded_in_place(pg_url: str, tmp_path: Path) -> None:
    with psycopg.connect(pg_url, autocommit=True) as conn:
        migrate(conn, "test", target=SCHEMA_VERSION - 1)
        conn.execute(
            "INSERT INTO results (time, inspection, camera, passed, data, duration_ms, "
            "config_hash, request_id, peer) VALUES (%s, 'old', 'cam', false, '{}', 2.0, "
            "'h', 5, 'p')",
            (T0,),
        )
    with PgResultLog(pg_url, spool=tmp_path / "spool.sqlite3") as log:
        (old,) = log.query()
        assert old.operator is None
        assert log.annotate(old.id, name="anna", choice="continue", reason="ok", at=T0 + 1)
        assert [r.id for r in log.query(operator="anna")] == [old.id]
    with psycopg.connect(pg_url) as conn:
        assert schema_version(conn) == SCHEMA_VERSION == 3
