"""Results annotated by operator in the SQLite result log (vision_server/results/sqlite.py):
an operator's answer written onto the failed result's row, a console try's user kept with its
row, the filter by operator read through its own index (query plans, 100,000 rows), and a log of
the previous schema version migrated in place with its rows kept."""

from __future__ import annotations

import sqlite3
from pathlib import Path

import pytest

from vision_server.results.sqlite import _MIGRATIONS, SCHEMA_VERSION, ResultEntry, ResultLog

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


def test_an_answer_is_written_onto_its_row_and_read_back(tmp_path: Path) -> None:
    with ResultLog(tmp_path / "r.sqlite3", store_images="none") as log:
        ids = [log.record(entry(i)) for i in range(6)]
        failed = ids[3]
        assert failed is not None
        assert failed > 0
        assert log.get(failed).operator is None  # type: ignore[union-attr]
        assert log.annotate(
            failed, name="anna", choice="continue", reason="cosmetic only", at=T0 + 100
        )
        row = log.get(failed)
        assert row is not None
        assert row.operator is not None
        assert row.operator.to_json() == {
            "name": "anna",
            "choice": "continue",
            "reason": "cosmetic only",
            "at": T0 + 100,
        }
        assert row.to_json()["operator"]["name"] == "anna"
        assert not log.annotate(999_999, name="anna", choice="retry", reason="", at=T0)
        # The other rows are untouched.
        assert [r.id for r in log.query(operator="anna")] == [failed]
        assert all(r.operator is None for r in log.query() if r.id != failed)


def test_a_try_keeps_its_user_and_the_filter_combines_with_the_others(tmp_path: Path) -> None:
    with ResultLog(tmp_path / "r.sqlite3", store_images="none") as log:
        for i in range(20):
            log.record(entry(i))
        try_id = log.record(entry(20, peer="console 127.0.0.1:5000", operator="ben"))
        assert try_id is not None
        row = log.get(try_id)
        assert row is not None
        assert row.is_try
        assert row.operator is not None
        assert row.operator.to_json() == {
            "name": "ben",
            "choice": None,
            "reason": None,
            "at": None,
        }
        for i in (3, 9, 15):
            log.annotate(i, name="anna", choice="continue", reason=f"r{i}", at=T0 + i)
        assert [r.id for r in log.query(operator="anna")] == [15, 9, 3]  # newest first
        # Row id n is entry(n - 1): rows 3, 9 and 15 are passes of "gap" at T0 + 2, 8, 14.
        assert [r.id for r in log.query(operator="anna", inspection="gap")] == [15, 9, 3]
        assert [r.id for r in log.query(operator="anna", inspection="magnet_check")] == []
        assert [r.id for r in log.query(operator="anna", passed=True)] == [15, 9, 3]
        assert [r.id for r in log.query(operator="anna", passed=False)] == []
        assert [r.id for r in log.query(operator="anna", since=T0 + 8)] == [15, 9]
        assert [r.id for r in log.query(operator="anna", before_id=15)] == [9, 3]
        assert [r.id for r in log.query(operator="anna", peer="10.0.0.7")] == [15, 9, 3]
        assert [r.id for r in log.query(operator="ben")] == [try_id]
        assert log.query(operator="nobody") == []


@pytest.mark.parametrize(
    "filters",
    [
        {},
        {"inspection": "magnet_check"},
        {"passed": False},
        {"inspection": "magnet_check", "passed": False},
        {"since": T0 + 5},
        {"peer": "10.0.0.7"},
    ],
    ids=["alone", "inspection", "verdict", "inspection+verdict", "since", "peer"],
)
def test_the_operator_filter_reads_through_its_index(
    tmp_path: Path, filters: dict[str, object]
) -> None:
    """With 100,000 rows, a page filtered by operator (with any other filter) is read through
    results_by_operator: the rows of that person only, never a scan of the log or of an
    inspection's rows."""
    with ResultLog(tmp_path / "r.sqlite3", store_images="none") as log:
        conn = log._conn
        conn.execute("BEGIN")
        conn.executemany(
            "INSERT INTO results (time, inspection, camera, passed, data, duration_ms, "
            "config_hash, request_id, peer) VALUES (?, ?, 'qc', ?, '{}', 1.0, 'h', ?, ?)",
            [
                (T0 + i, ("gap", "magnet_check")[i % 2], i % 3 != 0, i, f"10.0.0.7:{i}")
                for i in range(100_000)
            ],
        )
        conn.execute("COMMIT")
        for i in range(1, 100_000, 997):
            log.annotate(i, name="anna", choice="continue", reason="", at=T0)
        sql, params = log.query_sql(operator="anna", limit=51, **filters)  # type: ignore[arg-type]
        plan = " ".join(str(row[-1]) for row in conn.execute("EXPLAIN QUERY PLAN " + sql, params))
        assert "results_by_operator" in plan, plan
        assert "SCAN results" not in plan.replace("USING INDEX", ""), plan
        rows = log.query(operator="anna", limit=50, **filters)  # type: ignore[arg-type]
        assert rows
        assert all(r.operator is not None for r in rows)


def test_a_log_of_the_previous_schema_is_migrated_in_place(tmp_path: Path) -> None:
    path = tmp_path / "old.sqlite3"
    conn = sqlite3.connect(path, isolation_level=None)
    for script in _MIGRATIONS[: SCHEMA_VERSION - 1]:
        conn.executescript(script)
    conn.execute(f"PRAGMA user_version = {SCHEMA_VERSION - 1}")
    conn.execute(
        "INSERT INTO results (time, inspection, camera, passed, data, duration_ms, config_hash, "
        "request_id, peer) VALUES (?, 'magnet_check', 'qc', 0, '{\"v\": 1}', 2.0, 'h', 7, 'p')",
        (T0,),
    )
    conn.close()
    with ResultLog(path, store_images="none") as log:
        (old,) = log.query()
        assert old.data == {"v": 1}
        assert old.operator is None
        assert log.annotate(old.id, name="anna", choice="abort", reason="jammed", at=T0 + 1)
        assert [r.id for r in log.query(operator="anna")] == [old.id]
    check = sqlite3.connect(path)
    assert check.execute("PRAGMA user_version").fetchone()[0] == SCHEMA_VERSION
    indexes = {r[0] for r in check.execute("SELECT name FROM sqlite_master WHERE type='index'")}
    assert "results_by_operator" in indexes
    check.close()


def test_a_readonly_view_cannot_annotate(tmp_path: Path) -> None:
    path = tmp_path / "r.sqlite3"
    with ResultLog(path, store_images="none") as log:
        row_id = log.record(entry(1))
    assert row_id is not None
    with ResultLog.open_readonly(path) as view:
        from vision_server.results import ResultLogError

        with pytest.raises(ResultLogError, match="read-only"):
            view.annotate(row_id, name="anna", choice="retry", reason="", at=T0)
