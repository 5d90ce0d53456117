"""The result log: a real SQLite database and real files in tmp_path, real faults where possible."""

from __future__ import annotations

import errno
import io
import json
import logging
import signal
import sqlite3
import subprocess
import sys
import textwrap
import threading
import time
from datetime import UTC, datetime, timedelta
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pytest
from rich.console import Console

from vision_server.commands.results import parse_since, results_command
from vision_server.results import sqlite as results
from vision_server.results.sqlite import SCHEMA_VERSION, ResultEntry, ResultLog, ResultLogError

T0 = 1_700_000_000.0  # a fixed Unix time, so that the tests do not depend on the clock


def entry(
    n: int = 0,
    *,
    passed: bool = True,
    inspection: str = "presence",
    t: float | None = None,
    image: np.ndarray | None = None,
    error: str | None = None,
    data: dict[str, Any] | None = None,
) -> ResultEntry:
    return ResultEntry(
        time=T0 + n if t is None else t,
        inspection=inspection,
        camera="overhead",
        passed=passed,
        data={"n": n, "area_px": 1234.5} if data is None else data,
        duration_ms=3.25,
        config_hash="abc123",
        request_id=n,
        peer="10.0.0.7:50123",
        image=image,
        error=error,
    )


def noise_image(seed: int, shape: tuple[int, ...] = (32, 32, 3)) -> np.ndarray:
    """Incompressible, so that the PNG size is predictable (about the raw size)."""
    return np.random.default_rng(seed).integers(0, 256, shape, dtype=np.uint8)


@pytest.fixture
def db(tmp_path: Path) -> Path:
    return tmp_path / "logs" / "results.db"


# ---------------------------------------------------------------------- opening


def test_open_creates_directories_schema_and_wal(db: Path) -> None:
    with ResultLog(db) as log:
        assert log.image_dir == db.parent / "results-images"
        assert log.image_dir.is_dir()
    conn = sqlite3.connect(db)
    assert conn.execute("PRAGMA journal_mode").fetchone()[0] == "wal"
    assert conn.execute("PRAGMA user_version").fetchone()[0] == SCHEMA_VERSION
    conn.close()


def test_reopening_keeps_rows_and_image_accounting(db: Path) -> None:
    with ResultLog(db, store_images="all") as log:
        first = log.record(entry(1, image=noise_image(1)))
        stored = log.status().image_bytes
    with ResultLog(db, store_images="all") as log:
        assert [r.id for r in log.query()] == [first]
        assert log.status().image_bytes == stored > 0


def test_newer_schema_or_foreign_database_is_refused(tmp_path: Path) -> None:
    newer = tmp_path / "newer.db"
    conn = sqlite3.connect(newer)
    conn.execute(f"PRAGMA user_version = {SCHEMA_VERSION + 1}")
    conn.close()
    with pytest.raises(ResultLogError, match="newer"):
        ResultLog(newer)
    foreign = tmp_path / "foreign.db"
    conn = sqlite3.connect(foreign)
    conn.execute("CREATE TABLE parts (x)")
    conn.close()
    with pytest.raises(ResultLogError, match="not a result log"):
        ResultLog(foreign)


def test_older_schema_is_upgraded_in_place(db: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    with ResultLog(db) as log:
        first = log.record(entry(1))
    upgrade = "ALTER TABLE results ADD COLUMN station TEXT; -- a comment; with semicolons\n"
    monkeypatch.setattr(results, "_MIGRATIONS", (*results._MIGRATIONS, upgrade))
    with pytest.raises(ResultLogError, match="open it once with the server"):
        ResultLog.open_readonly(db)
    with ResultLog(db) as log:
        assert [r.id for r in log.query()] == [first]
        assert log.record(entry(2)) is not None
    conn = sqlite3.connect(db)
    assert conn.execute("PRAGMA user_version").fetchone()[0] == SCHEMA_VERSION + 1
    assert "station" in [col[1] for col in conn.execute("PRAGMA table_info(results)")]
    conn.close()
    with ResultLog.open_readonly(db) as view:
        assert view.count() == 2


def test_unopenable_path_is_a_typed_error(tmp_path: Path) -> None:
    (tmp_path / "file").write_text("x")
    with pytest.raises(ResultLogError, match="cannot open"):
        ResultLog(tmp_path / "file" / "results.db")


def test_bad_arguments() -> None:
    with pytest.raises(ValueError, match="store_images"):
        ResultLog(Path("x.db"), store_images="some")  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="max_image_bytes"):
        ResultLog(Path("x.db"), max_image_bytes=-1)


# ---------------------------------------------------------------------- recording and querying


def test_record_round_trips_every_field(db: Path) -> None:
    data = {
        "count": np.int64(3),
        "centre_px": np.array([12.5, 40.25]),
        "score": np.float32(0.5),
        "ok": True,
        "nested": {"a": [1, 2]},
        "nan": float("nan"),
    }
    with ResultLog(db) as log:
        new_id = log.record(entry(7, passed=False, error="camera timeout", data=data))
        assert isinstance(new_id, int)
        (row,) = log.query()
    assert row.id == new_id
    assert (row.time, row.inspection, row.camera, row.passed) == (
        T0 + 7,
        "presence",
        "overhead",
        False,
    )
    assert (row.duration_ms, row.config_hash, row.request_id, row.peer, row.error) == (
        3.25,
        "abc123",
        7,
        "10.0.0.7:50123",
        "camera timeout",
    )
    assert row.data["count"] == 3
    assert row.data["centre_px"] == [12.5, 40.25]
    assert row.data["score"] == 0.5
    assert row.data["nested"] == {"a": [1, 2]}
    assert np.isnan(row.data["nan"])
    assert row.image_path is None
    assert json.loads(json.dumps(row.to_json()))["verdict"] == "fail"


def test_query_filters_order_limit_and_count(db: Path) -> None:
    with ResultLog(db) as log:
        for n in range(10):
            log.record(entry(n, passed=n % 3 != 0, inspection="locate" if n % 2 else "presence"))
        assert log.count() == 10
        assert [r.request_id for r in log.query(limit=3)] == [9, 8, 7]
        assert [r.request_id for r in log.query(limit=3, newest_first=False)] == [0, 1, 2]
        assert [r.request_id for r in log.query(since=T0 + 7)] == [9, 8, 7]
        assert [r.request_id for r in log.query(inspection="locate")] == [9, 7, 5, 3, 1]
        assert [r.request_id for r in log.query(passed=False)] == [9, 6, 3, 0]
        assert [r.request_id for r in log.query(inspection="locate", passed=False)] == [9, 3]
        assert log.count(inspection="presence", since=T0 + 4) == 3
        assert log.query(limit=0) == []
        assert log.query(inspection="nothing") == []
        # Ordered by the inspection's time, not by arrival.
        late = log.record(entry(100, t=T0 - 1))
        assert log.query(newest_first=False, limit=1)[0].id == late


def test_concurrent_records_from_threads_lose_nothing(db: Path) -> None:
    threads, per_thread = 8, 60
    ids: list[int | None] = []
    ids_lock = threading.Lock()
    with ResultLog(db, store_images="failures") as log:

        def work(k: int) -> None:
            for i in range(per_thread):
                n = k * 1000 + i
                img = noise_image(n, (8, 8, 3)) if i % 5 == 0 else None
                got = log.record(entry(n, passed=i % 5 != 0, image=img))
                with ids_lock:
                    ids.append(got)

        pool = [threading.Thread(target=work, args=(k,)) for k in range(threads)]
        for t in pool:
            t.start()
        for t in pool:
            t.join()
        assert None not in ids
        assert len(set(ids)) == threads * per_thread
        assert log.count() == threads * per_thread
        assert {r.request_id for r in log.query(limit=10_000)} == {
            k * 1000 + i for k in range(threads) for i in range(per_thread)
        }
        failures = log.query(passed=False, limit=10_000)
        assert len(failures) == threads * per_thread // 5
        assert all(r.image_path is not None and r.image_path.is_file() for r in failures)
        assert log.errors == 0
        assert log.status().recorded == threads * per_thread


# ---------------------------------------------------------------------- images


@pytest.mark.parametrize(
    ("policy", "stored_for_pass", "stored_for_fail"),
    [("none", False, False), ("failures", False, True), ("all", True, True)],
)
def test_image_policies(
    db: Path, policy: results.ImagePolicy, stored_for_pass: bool, stored_for_fail: bool
) -> None:
    with ResultLog(db, store_images=policy) as log:
        ok = log.record(entry(1, passed=True, image=noise_image(1)))
        bad = log.record(entry(2, passed=False, image=noise_image(2)))
        rows = {r.id: r for r in log.query()}
        assert (rows[ok].image_path is not None) is stored_for_pass
        assert (rows[bad].image_path is not None) is stored_for_fail
        assert log.status().images_stored == stored_for_pass + stored_for_fail


def test_failed_request_with_image_counts_as_failure(db: Path) -> None:
    with ResultLog(db, store_images="failures") as log:
        log.record(entry(1, passed=True, error="deadline exceeded", image=noise_image(1)))
        assert log.query()[0].image_path is not None


@pytest.mark.parametrize(
    "image",
    [
        noise_image(3, (20, 30, 3)),
        noise_image(4, (20, 30)),
        (np.arange(600, dtype=np.uint16).reshape(20, 30) * 100),
    ],
    ids=["bgr8", "grey8", "grey16"],
)
def test_stored_image_is_the_input_as_png(db: Path, image: np.ndarray) -> None:
    with ResultLog(db, store_images="all") as log:
        log.record(entry(1, image=image))
        path = log.query()[0].image_path
    assert path is not None
    assert path.suffix == ".png"
    assert path.parent.parent == db.parent / "results-images"
    back = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    np.testing.assert_array_equal(back, image)
    assert not list(path.parent.glob(".*.tmp"))


def test_image_names_never_come_from_the_client(db: Path) -> None:
    hostile = "../../../etc/passwd"
    with ResultLog(db, store_images="all") as log:
        log.record(
            ResultEntry(
                T0, hostile, hostile, False, {}, 1.0, hostile, peer=hostile, image=noise_image(1)
            )
        )
        path = log.query()[0].image_path
        assert path is not None
        assert path.resolve().is_relative_to(log.image_dir.resolve())
        assert "passwd" not in path.name
        assert log.query()[0].inspection == hostile


def test_bad_image_is_counted_and_the_row_still_recorded(db: Path) -> None:
    with ResultLog(db, store_images="all") as log:
        new_id = log.record(entry(1, image=np.zeros((4, 4), np.float64)))
        assert new_id is not None
        assert log.query()[0].image_path is None
        assert log.errors == 1
        assert "uint8 or uint16" in (log.status().last_error or "")


# ---------------------------------------------------------------------- disk cap


def test_disk_cap_deletes_the_oldest_images_and_keeps_the_rows(db: Path) -> None:
    size = len(cv2.imencode(".png", noise_image(0))[1])
    cap = int(size * 3.5)  # room for three images
    with ResultLog(db, store_images="all", max_image_bytes=cap) as log:
        ids = [log.record(entry(n, image=noise_image(n))) for n in range(6)]
        rows = {r.id: r for r in log.query()}
        with_image = [i for i in ids if rows[i].image_path is not None]
        assert with_image == ids[-3:]
        assert len(rows) == 6  # rows stay, only their images go
        files = sorted(log.image_dir.rglob("*.png"))
        assert len(files) == 3
        assert sum(f.stat().st_size for f in files) <= cap
        status = log.status()
        assert status.image_bytes == sum(f.stat().st_size for f in files)
        assert (status.images_stored, status.images_deleted) == (6, 3)
        assert log.errors == 0


def test_image_larger_than_the_cap_is_not_stored(db: Path) -> None:
    with ResultLog(db, store_images="all", max_image_bytes=100) as log:
        assert log.record(entry(1, image=noise_image(1))) is not None
        assert log.query()[0].image_path is None
        assert log.status().images_skipped == 1
        assert not list(log.image_dir.rglob("*.png"))


def test_cap_never_deletes_outside_the_image_directory(db: Path, tmp_path: Path) -> None:
    victim = tmp_path / "victim.png"
    victim.write_bytes(b"precious")
    with ResultLog(db, store_images="all", max_image_bytes=10_000) as log:
        log.record(entry(1))
    # A tampered database pointing a row at a file outside the image directory.
    conn = sqlite3.connect(db)
    conn.execute(
        "UPDATE results SET image = ?, image_bytes = 9000",
        (str(Path("..") / ".." / "victim.png"),),
    )
    conn.commit()
    conn.close()
    with ResultLog(db, store_images="all", max_image_bytes=10_000) as log:
        assert log.query()[0].image_path is None
        assert log.record(entry(2, image=noise_image(2))) is not None
    assert victim.read_bytes() == b"precious"


# ---------------------------------------------------------------------- faults


def test_image_directory_fault_still_records_the_row(db: Path) -> None:
    with ResultLog(db, store_images="all") as log:
        # A file where the image directory should be: every image write fails, even as root.
        log.image_dir.rmdir()
        log.image_dir.write_text("in the way")
        first = log.record(entry(1, image=noise_image(1)))
        assert first is not None
        assert log.errors == 1
        assert log.query()[0].image_path is None
        log.image_dir.unlink()  # the fault clears
        second = log.record(entry(2, image=noise_image(2)))
        row = log.query()[0]
        assert row.id == second
        assert row.image_path is not None
        assert row.image_path.is_file()
        assert log.errors == 1


def test_disk_full_on_images_is_reported(db: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    def full(path: Path, payload: bytes) -> None:
        raise OSError(errno.ENOSPC, "No space left on device")

    with ResultLog(db, store_images="all") as log:
        monkeypatch.setattr(results, "_write_atomically", full)
        assert log.record(entry(1, image=noise_image(1))) is not None
        assert "disk full" in (log.status().last_error or "")
        assert log.errors == 1


def test_database_full_returns_none_logs_once_and_recovers(
    db: Path, monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture
) -> None:
    connections: list[sqlite3.Connection] = []
    real_connect = results._connect

    def connect(path: Path, *, readonly: bool, busy_timeout_s: float) -> sqlite3.Connection:
        conn = real_connect(path, readonly=readonly, busy_timeout_s=busy_timeout_s)
        connections.append(conn)
        return conn

    monkeypatch.setattr(results, "_connect", connect)
    caplog.set_level(logging.DEBUG, logger="vision_server.results")
    big = {"features": "x" * 3000}
    with ResultLog(db, store_images="failures") as log:
        (conn,) = connections
        pages = conn.execute("PRAGMA page_count").fetchone()[0]
        # SQLite's own limit on the file size: inserts fail with SQLITE_FULL, as on a full disk.
        conn.execute(f"PRAGMA max_page_count = {pages + 2}")
        got = [log.record(entry(n, data=big)) for n in range(12)]
        assert None in got
        failed = got.count(None)
        assert log.errors == failed
        assert "full" in (log.status().last_error or "")
        errors_logged = [r for r in caplog.records if r.levelno == logging.ERROR]
        assert len(errors_logged) == 1  # the first fault loudly, the rest quietly
        # An image written for a row that then failed is removed again.
        assert log.record(entry(99, passed=False, data=big, image=noise_image(9))) is None
        assert not list(log.image_dir.rglob("*.png"))

        conn.execute("PRAGMA max_page_count = 1073741823")  # the disk has room again
        recovered = log.record(entry(100, data=big))
        assert recovered is not None
        assert log.query()[0].id == recovered
        assert any("recovered" in r.getMessage() for r in caplog.records)
        assert log.count() == 12 - failed + 1


def test_locked_database_returns_none_then_recovers(db: Path) -> None:
    with ResultLog(db, busy_timeout_s=0.05) as log:
        other = sqlite3.connect(db, isolation_level=None)
        other.execute("BEGIN EXCLUSIVE")
        assert log.record(entry(1)) is None
        assert log.errors == 1
        assert "locked" in (log.status().last_error or "")
        other.execute("COMMIT")
        other.close()
        assert log.record(entry(2)) is not None
        assert log.count() == 1


def test_health_turns_not_ok_on_a_lost_row_and_stays_so_until_reopened(
    db: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    connections: list[sqlite3.Connection] = []
    real_connect = results._connect

    def connect(path: Path, *, readonly: bool, busy_timeout_s: float) -> sqlite3.Connection:
        conn = real_connect(path, readonly=readonly, busy_timeout_s=busy_timeout_s)
        connections.append(conn)
        return conn

    monkeypatch.setattr(results, "_connect", connect)
    big = {"features": "x" * 3000}
    with ResultLog(db, store_images="all") as log:
        (conn,) = connections
        assert log.health() == {
            "ok": True,
            "written": 0,
            "failed": 0,
            "failing": False,
            "images_failed": 0,
            "last_error": None,
            "last_error_time": None,
        }
        # An image lost, the row written: the result is in the log, health stays ok.
        assert log.record(entry(1, image=np.zeros((2, 2), np.float64))) is not None
        health = log.health()
        assert (health["ok"], health["written"], health["images_failed"]) == (True, 1, 1)

        pages = conn.execute("PRAGMA page_count").fetchone()[0]
        conn.execute(f"PRAGMA max_page_count = {pages + 2}")  # SQLITE_FULL, as on a full disk
        got = [log.record(entry(n, data=big)) for n in range(2, 14)]
        lost = got.count(None)
        assert lost
        health = log.health()
        assert health["ok"] is False
        assert health["failed"] == lost
        assert health["written"] == 1 + len(got) - lost
        assert health["failing"] is True
        assert "SQLITE_FULL" in health["last_error"]
        assert isinstance(health["last_error_time"], float)

        conn.execute("PRAGMA max_page_count = 1073741823")  # room again
        assert log.record(entry(20)) is not None
        health = log.health()
        assert health["failing"] is False
        assert health["ok"] is False  # sticky: the lost rows stay lost
        assert health["failed"] == lost
    with ResultLog(db) as reopened:  # a restart starts afresh
        assert reopened.health()["ok"] is True


@pytest.mark.parametrize(
    ("setup", "target", "store_images", "reason"),
    [
        ("file:plain", "plain/results.db", "none", "Not a directory"),
        ("file:plain", "plain/deeper/results.db", "none", "Not a directory"),
        ("dir:results.db", "results.db", "none", "Is a directory"),
        ("file:results-images", "results.db", "failures", "Not a directory"),
        ("", "new/dirs/results.db", "all", None),
        ("file:results-images", "results.db", "none", None),  # no images: no image directory
        ("file:results.db", "results.db", "failures", None),  # an existing (empty) database
    ],
)
def test_check_creatable_names_the_os_error_and_creates_nothing(
    tmp_path: Path, setup: str, target: str, store_images: str, reason: str | None
) -> None:
    kind, _, name = setup.partition(":")
    if kind == "file":
        (tmp_path / name).write_text("")
    elif kind == "dir":
        (tmp_path / name).mkdir()
    before = sorted(tmp_path.rglob("*"))
    if reason is None:
        results.check_creatable(tmp_path / target, store_images=store_images)  # type: ignore[arg-type]
    else:
        with pytest.raises(ResultLogError, match=reason) as info:
            results.check_creatable(tmp_path / target, store_images=store_images)  # type: ignore[arg-type]
        assert str(tmp_path / target) in str(info.value)
    assert sorted(tmp_path.rglob("*")) == before


def test_open_names_the_os_error_not_sqlites(tmp_path: Path) -> None:
    (tmp_path / "results.db").mkdir()
    with pytest.raises(ResultLogError, match=r"\[Errno 21\] Is a directory"):
        ResultLog(tmp_path / "results.db")
    (tmp_path / "plain").write_text("")
    with pytest.raises(ResultLogError, match=r"\[Errno 20\] Not a directory"):
        ResultLog(tmp_path / "plain" / "results.db")


def test_strange_entries_are_faults_not_exceptions(db: Path) -> None:
    circular: dict[str, Any] = {}
    circular["self"] = circular
    strange = [
        entry(1, data=circular),
        entry(2, t=float("nan"), passed=False, image=noise_image(2)),
        ResultEntry(T0, "presence", "cam", True, {}, 1.0, "h", request_id=2**70),
        entry(3, data={("tuple", "key"): 1}),  # type: ignore[dict-item]
    ]
    with ResultLog(db, store_images="all") as log:
        assert [log.record(e) for e in strange] == [None] * len(strange)
        assert log.errors == len(strange)
        assert log.record(entry(4)) is not None
        assert not list(log.image_dir.rglob("*.png"))


def test_record_after_close_returns_none(db: Path) -> None:
    log = ResultLog(db)
    log.close()
    log.close()
    assert log.record(entry(1)) is None
    assert log.errors == 1
    with pytest.raises(ResultLogError, match="closed"):
        log.query()


# ---------------------------------------------------------------------- read-only view


def test_readonly_of_a_missing_log_creates_nothing(tmp_path: Path) -> None:
    missing = tmp_path / "nowhere" / "results.db"
    with pytest.raises(ResultLogError, match="no result log"):
        ResultLog.open_readonly(missing)
    assert not (tmp_path / "nowhere").exists()


def test_readonly_view_reads_while_a_writer_writes(db: Path) -> None:
    total = 300
    with ResultLog(db) as writer:
        writer.record(entry(0))
        view = ResultLog.open_readonly(db)
        done = threading.Event()
        seen: list[int] = []

        def write() -> None:
            for n in range(1, total):
                writer.record(entry(n))
            done.set()

        thread = threading.Thread(target=write)
        thread.start()
        while not done.is_set():
            seen.append(view.count())
        thread.join()
        seen.append(view.count())
        assert seen == sorted(seen)  # never goes back, never errors
        assert seen[-1] == total
        assert view.query(limit=1)[0].request_id == total - 1
        with pytest.raises(ResultLogError, match="read-only"):
            view.record(entry(1))
        view.close()


def test_readonly_view_finds_a_custom_image_dir(tmp_path: Path) -> None:
    db, images = tmp_path / "r.db", tmp_path / "elsewhere"
    with ResultLog(db, store_images="all", image_dir=images) as log:
        log.record(entry(1, image=noise_image(1)))
    with ResultLog.open_readonly(db) as view:
        path = view.query()[0].image_path
    assert path is not None
    assert path.is_file()
    assert path.resolve().is_relative_to(images.resolve())


# ---------------------------------------------------------------------- durability

_WRITER = textwrap.dedent(
    """
    import sys, threading, time
    from pathlib import Path
    import numpy as np
    from vision_server.results import ResultEntry, ResultLog

    log = ResultLog(Path(sys.argv[1]), store_images="failures", max_image_bytes=200_000)
    image = np.random.default_rng(0).integers(0, 256, (24, 32, 3), dtype=np.uint8)
    out = threading.Lock()

    def work(k):
        for i in range(1_000_000):
            n = k * 10_000_000 + i
            new_id = log.record(ResultEntry(time.time(), "presence", "cam", i % 4 != 0,
                                            {"n": n}, 1.0, "h", request_id=n, image=image))
            if new_id is None:
                sys.exit(3)
            with out:  # the "response" goes out only after record returned
                sys.stdout.write(f"{new_id}\\n")
                sys.stdout.flush()

    threads = [threading.Thread(target=work, args=(k,)) for k in range(4)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    """
)


@pytest.mark.slow
def test_sigkill_mid_burst_loses_no_acknowledged_result(db: Path) -> None:
    proc = subprocess.Popen(
        [sys.executable, "-c", _WRITER, str(db)],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    acknowledged: list[int] = []
    try:
        assert proc.stdout is not None
        # Not a round number: a log that committed every 10 or 100 records would be caught.
        while len(acknowledged) < 1013:
            line = proc.stdout.readline()
            if not line:
                break
            acknowledged.append(int(line))
        proc.send_signal(signal.SIGKILL)
        rest, stderr = proc.communicate(timeout=30)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    assert proc.returncode == -signal.SIGKILL, stderr  # killed mid-burst, not finished
    # Lines printed after our 1000th were acknowledged too; a cut-off last line was not.
    acknowledged += [int(x) for x in rest.split("\n")[:-1]]
    assert len(acknowledged) >= 1000

    conn = sqlite3.connect(db)
    assert conn.execute("PRAGMA integrity_check").fetchone()[0] == "ok"
    stored = {row[0] for row in conn.execute("SELECT id FROM results")}
    conn.close()
    missing = set(acknowledged) - stored
    assert not missing, f"{len(missing)} acknowledged results lost, e.g. {sorted(missing)[:5]}"

    with ResultLog(db) as log:  # the writer's next start: images of stored rows are complete
        images = [r.image_path for r in log.query(passed=False, limit=100_000) if r.image_path]
        assert images
        for path in images:
            assert cv2.imread(str(path)) is not None, path
        assert not list(log.image_dir.rglob(".*.tmp"))


# ---------------------------------------------------------------------- command line


def test_parse_since_relative_durations() -> None:
    now = 1_000_000.0
    assert parse_since("10m", now=now) == now - 600
    assert parse_since("2h", now=now) == now - 7200
    assert parse_since("1d", now=now) == now - 86400
    assert parse_since("1h30m", now=now) == now - 5400
    assert parse_since(" 90S ", now=now) == now - 90
    assert parse_since("1.5h", now=now) == now - 5400


def test_parse_since_iso_dates() -> None:
    utc = datetime(2024, 5, 1, 8, 30, tzinfo=UTC).timestamp()
    assert parse_since("2024-05-01T08:30:00+00:00") == utc
    assert parse_since("2024-05-01T08:30Z") == parse_since("2024-05-01 10:30+02:00")
    local_midnight = datetime(2024, 5, 1).timestamp()  # naive: local time
    assert parse_since("2024-05-01") == local_midnight
    assert parse_since("2024-05-01T06:00") == local_midnight + timedelta(hours=6).total_seconds()


@pytest.mark.parametrize("bad", ["", "yesterday", "10", "-5m", "5 minutes", "2024-13-01", "m"])
def test_parse_since_rejects_bad_values(bad: str) -> None:
    with pytest.raises(ValueError, match="--since"):
        parse_since(bad)


def _consoles() -> tuple[Console, io.StringIO, Console, io.StringIO]:
    out, err = io.StringIO(), io.StringIO()
    return (
        Console(file=out, width=200, color_system=None),
        out,
        Console(file=err, width=200, color_system=None),
        err,
    )


def _filled(db: Path) -> None:
    now = time.time()
    with ResultLog(db, store_images="failures") as log:
        log.record(entry(1, t=now - 7200, inspection="locate"))
        log.record(entry(2, t=now - 60, passed=False, image=noise_image(2)))
        log.record(entry(3, t=now - 30, data={"holes": [1, 2, 3], "ok": True, "d_mm": 1.23456}))


def test_results_command_json_lines(db: Path) -> None:
    _filled(db)
    console, out, err_console, _ = _consoles()
    code = results_command(
        db,
        since="1h",
        inspection=None,
        json_out=True,
        limit=10,
        failed_only=False,
        console=console,
        err_console=err_console,
    )
    assert code == 0
    lines = [json.loads(line) for line in out.getvalue().splitlines()]
    assert [line["request_id"] for line in lines] == [3, 2]
    assert lines[1]["verdict"] == "fail"
    assert lines[1]["image_path"]
    assert Path(lines[1]["image_path"]).is_file()
    assert lines[0]["data"] == {"holes": [1, 2, 3], "ok": True, "d_mm": 1.23456}
    assert set(lines[0]) >= {"time", "time_iso", "inspection", "camera", "duration_ms"}


def test_results_command_filters(db: Path) -> None:
    _filled(db)
    console, out, err_console, _ = _consoles()
    kwargs: dict[str, Any] = {"json_out": True, "console": console, "err_console": err_console}
    assert (
        results_command(db, since=None, inspection=None, limit=10, failed_only=True, **kwargs) == 0
    )
    assert [json.loads(x)["request_id"] for x in out.getvalue().splitlines()] == [2]
    out.seek(0)
    out.truncate()
    assert (
        results_command(db, since=None, inspection="locate", limit=10, failed_only=False, **kwargs)
        == 0
    )
    assert [json.loads(x)["request_id"] for x in out.getvalue().splitlines()] == [1]


def test_results_command_table(db: Path) -> None:
    _filled(db)
    console, out, err_console, _ = _consoles()
    code = results_command(
        db,
        since=None,
        inspection=None,
        json_out=False,
        limit=2,
        failed_only=False,
        console=console,
        err_console=err_console,
    )
    assert code == 0
    text = out.getvalue()
    assert "FAIL" in text
    assert "PASS" in text
    assert "holes=[3] ok=true d_mm=1.235" in text
    assert "2 of 3 matching" in text
    assert "locate" not in text  # the limit cut the oldest


def test_results_command_errors(db: Path, tmp_path: Path) -> None:
    console, out, err_console, err = _consoles()
    common: dict[str, Any] = {
        "inspection": None,
        "json_out": True,
        "limit": 10,
        "failed_only": False,
        "console": console,
        "err_console": err_console,
    }
    # With --json, errors are the one JSON error shape on stdout; a missing log is a usage
    # error (exit 2: exit 1 means a fail verdict, docs/integrator-guide.md §6).
    missing = tmp_path / "missing.db"
    assert results_command(missing, since=None, **common) == 2
    assert not missing.exists()
    error = json.loads(out.getvalue())["error"]
    assert error["kind"] == "usage"
    assert "no result log" in error["message"]
    _filled(db)
    out.truncate(0)
    out.seek(0)
    assert results_command(db, since="last tuesday", **common) == 2
    assert "--since" in json.loads(out.getvalue())["error"]["message"]
    assert err.getvalue() == ""
    # Without --json they go to standard error as text.
    assert results_command(missing, since=None, **{**common, "json_out": False}) == 2
    assert "no result log" in err.getvalue()
