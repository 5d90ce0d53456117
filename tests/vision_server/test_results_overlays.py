"""The result log keeps the inspection's overlay beside the stored input: a second PNG under the
same policy, disk cap and path rules; older logs are upgraded in place."""

from __future__ import annotations

import sqlite3
from pathlib import Path

import cv2
import numpy as np
import pytest

from vision_server.results import sqlite as results
from vision_server.results.sqlite import SCHEMA_VERSION, ResultEntry, ResultLog

T0 = 1_700_000_000.0


def noise(seed: int, shape: tuple[int, ...] = (32, 32, 3)) -> np.ndarray:
    """Incompressible, so that a PNG's size is about the raw size."""
    return np.random.default_rng(seed).integers(0, 256, shape, dtype=np.uint8)


def entry(
    n: int, *, passed: bool = False, image: np.ndarray | None = None, overlay: np.ndarray | None
) -> ResultEntry:
    return ResultEntry(
        time=T0 + n,
        inspection="magnet_check",
        camera="qc",
        passed=passed,
        data={"n": n},
        duration_ms=1.5,
        config_hash="abc",
        request_id=n,
        peer="10.0.0.7:50123",
        image=noise(n) if image is None else image,
        overlay=overlay,
    )


@pytest.fixture
def db(tmp_path: Path) -> Path:
    return tmp_path / "results.db"


def test_the_overlay_is_stored_as_png_beside_the_input(db: Path) -> None:
    image, overlay = noise(1), noise(2)
    with ResultLog(db, store_images="failures") as log:
        row_id = log.record(entry(1, image=image, overlay=overlay))
        assert row_id is not None
        row = log.get(row_id)
        assert row is not None
        assert row.image_path is not None
        assert row.overlay_path is not None
        assert row.overlay_path != row.image_path
        assert row.overlay_path.parent.parent == log.image_dir
        stored = cv2.imread(str(row.overlay_path), cv2.IMREAD_UNCHANGED)
        np.testing.assert_array_equal(stored, overlay)
        np.testing.assert_array_equal(cv2.imread(str(row.image_path), cv2.IMREAD_UNCHANGED), image)
        # The disk accounting counts both files.
        sizes = row.image_path.stat().st_size + row.overlay_path.stat().st_size
        assert log.status().image_bytes == sizes
        assert row.to_json()["overlay_path"] == str(row.overlay_path)


def test_the_overlay_follows_the_image_policy(db: Path) -> None:
    with ResultLog(db, store_images="failures") as log:
        passed = log.get(log.record(entry(1, passed=True, overlay=noise(3))) or 0)
        without = log.get(log.record(entry(2, overlay=None)) or 0)
    assert passed is not None
    assert passed.image_path is None
    assert passed.overlay_path is None
    assert without is not None
    assert without.image_path is not None
    assert without.overlay_path is None
    with ResultLog(db.with_name("none.db"), store_images="none") as log:
        assert not log.keeps_images
        row = log.get(log.record(entry(3, overlay=noise(4))) or 0)
        assert row is not None
        assert row.overlay_path is None
        assert not any(log.image_dir.glob("*/*.png"))


def test_the_disk_cap_deletes_the_overlay_with_its_input(db: Path) -> None:
    one = len(cv2.imencode(".png", noise(0))[1])
    # Room for two rows with overlays (four files), not three.
    with ResultLog(db, store_images="all", max_image_bytes=int(one * 4.5)) as log:
        ids = [log.record(entry(n, overlay=noise(100 + n))) for n in range(3)]
        oldest, *newer = (log.get(i or 0) for i in ids)
        assert oldest is not None
        assert oldest.image_path is None
        assert oldest.overlay_path is None
        assert all(r is not None and r.overlay_path is not None for r in newer)
        files = sorted(log.image_dir.glob("*/*.png"))
        assert len(files) == 4
        assert log.status().image_bytes == sum(f.stat().st_size for f in files)
        assert log.status().images_deleted == 1


def test_an_overlay_that_does_not_fit_beside_its_input_is_dropped(db: Path) -> None:
    one = len(cv2.imencode(".png", noise(0))[1])
    with ResultLog(db, store_images="all", max_image_bytes=int(one * 1.5)) as log:
        row = log.get(log.record(entry(1, overlay=noise(2))) or 0)
        assert row is not None
        assert row.image_path is not None
        assert row.overlay_path is None
        assert log.status().images_skipped == 1
        assert len(list(log.image_dir.glob("*/*.png"))) == 1


def test_a_bad_overlay_is_a_counted_fault_and_the_row_keeps_its_input(db: Path) -> None:
    with ResultLog(db, store_images="all") as log:
        row = log.get(log.record(entry(1, overlay=np.zeros((4, 4), np.float32))) or 0)
        assert row is not None
        assert row.image_path is not None
        assert row.overlay_path is None
        assert log.status().images_failed == 1
        assert log.health()["ok"]


def test_an_overlay_name_from_an_edited_database_is_not_followed(db: Path) -> None:
    with ResultLog(db, store_images="all") as log:
        row_id = log.record(entry(1, overlay=noise(2)))
    conn = sqlite3.connect(db)
    conn.execute("UPDATE results SET overlay = '../../etc/passwd' WHERE id = ?", (row_id,))
    conn.commit()
    conn.close()
    with ResultLog.open_readonly(db) as view:
        row = view.get(row_id or 0)
        assert row is not None
        assert row.overlay_path is None


def test_a_version_1_log_is_upgraded_and_keeps_its_rows(db: Path) -> None:
    # A log as a server before stored overlays left it: schema 1, one row with its input.
    name = "2023-11-14/" + "ab" * 16 + ".png"
    image_file = db.with_name("results-images") / name
    image_file.parent.mkdir(parents=True)
    image_file.write_bytes(cv2.imencode(".png", noise(1))[1].tobytes())
    conn = sqlite3.connect(db)
    conn.executescript(results._MIGRATIONS[0])
    conn.execute(
        "INSERT INTO results (time, inspection, camera, passed, data, duration_ms, config_hash, "
        "image, image_bytes) VALUES (?, 'magnet_check', 'qc', 0, '{}', 1.0, 'abc', ?, ?)",
        (T0, name, image_file.stat().st_size),
    )
    conn.execute("PRAGMA user_version = 1")
    conn.commit()
    conn.close()
    with ResultLog(db, store_images="all") as log:
        (row,) = log.query()
        assert row.image_path == image_file
        assert row.overlay_path is None  # written before overlays were stored
        newer = log.get(log.record(entry(2, overlay=noise(3))) or 0)
        assert newer is not None
        assert newer.overlay_path is not None
    conn = sqlite3.connect(db)
    assert conn.execute("PRAGMA user_version").fetchone()[0] == SCHEMA_VERSION
    indexes = {r[0] for r in conn.execute("SELECT name FROM sqlite_master WHERE type = 'index'")}
    assert {"results_by_verdict", "results_by_inspection_verdict", "results_by_peer"} <= indexes
