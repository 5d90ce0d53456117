"""The result log: every answered inspection in a SQLite database, images of failures on disk.

One row per inspection (time, inspection, camera, verdict, measures or features as JSON, duration,
config hash, request id, peer, error) and, depending on the policy, the input image as a PNG file
beside the database, with the inspection's overlay (its drawing over the input) as a second PNG.
The server calls :meth:`ResultLog.record` from its worker threads and sends the response only
after it returned, and the response says whether the row was written (RESULT's ``stored``, SPEC
§6.3): a result acknowledged with ``stored: true`` is in the log.

This is the cell's own log; :mod:`.postgres` keeps the same rows in PostgreSQL for a plant.
Both implement :class:`.store.ResultStore`, which the server, the console and
``vision-server results`` use (:mod:`.configured` picks one).

Choices, and why:

- **Durability.** WAL journal with ``synchronous=NORMAL``: a commit appends to the WAL file with
  ``write()`` and returns; the data is then in the operating system's page cache, which survives
  the death of the process (SIGKILL, a crash, the OOM killer). Only a power loss or a kernel panic
  can lose the last transactions before a checkpoint syncs them, and never corrupts the database.
  ``FULL`` would add an ``fsync`` per inspection (milliseconds on a cell PC's SSD) to protect
  against power loss alone; the cell's UPS is the better answer to that.
- **Faults never stop inspections, and are never silent.** A full disk, an I/O error, a locked
  or read-only database: :meth:`~ResultLog.record` logs the error (``vision_server.results``),
  counts the lost row in ``failed`` and returns ``None``; the server answers with ``stored:
  false`` and reports itself unhealthy (:meth:`ResultLog.health`). The next call tries again, so
  the log takes rows again by itself when the fault clears. If only the image cannot be written,
  the row is still recorded (without an image) and the fault is counted in ``images_failed``:
  the verdict matters more than the picture.
- **Health is sticky.** Once a row was lost, :meth:`~ResultLog.health` says ``ok: false`` until
  the log is reopened (a server restart), even after writes succeed again: the health check is
  polled, and a fault that cleared between two polls would otherwise never be seen, while the
  lost rows stay lost. ``failing`` tells whether the latest write failed (the fault is ongoing).
- **Disk cap for images.** When the stored images exceed ``max_image_bytes``, the *oldest* images
  are deleted and their rows keep everything but the image reference (set to NULL). The newest
  failures are what an operator looks at; stopping at the cap would keep last month's instead.
  An image larger than the whole cap is not stored at all. A row's overlay counts towards the
  cap with its input and goes with it; an overlay that would not fit beside its input is
  dropped (the input is kept: it is what a try re-runs on).
- **Overlays cost a second PNG.** Encoding is in :meth:`~ResultLog.record`, i.e. in the worker
  that ran the inspection, never on the event loop; it roughly doubles the log's encoding time
  for stored rows (the bench measures it), and nothing for rows whose images are not stored.
- **Paths.** Image file names are made here (``<YYYY-MM-DD>/<uuid>.png`` under the image
  directory), never from a client's strings, and names read back from the database are checked
  against that pattern before they are opened or deleted.
- **One writer.** One process writes a log (the server); any number of read-only views
  (:meth:`ResultLog.open_readonly`, used by ``vision-server results``) read it at the same time.
"""

from __future__ import annotations

import contextlib
import errno
import logging
import os
import re
import sqlite3
import threading
import time
import uuid
from dataclasses import dataclass
from datetime import UTC, datetime
from pathlib import Path
from types import TracebackType
from typing import Any, get_args

import cv2
import numpy as np

from .query import COLUMNS, OPERATOR_COLUMNS, page_sql, timing_sql
from .query import where_sql as _where
from .store import (
    ImagePolicy,
    OperatorMark,
    ResultEntry,
    ResultLogError,
    StoredResult,
    TimingRows,
    is_row_id,
    parse_data,
    row_values,
)

__all__ = [
    "SCHEMA_VERSION",
    "ImagePolicy",
    "LogStatus",
    "ResultEntry",
    "ResultLog",
    "ResultLogError",
    "StoredResult",
    "check_creatable",
]

logger = logging.getLogger("vision_server.results")

GIB = 1 << 30

# Each entry upgrades the schema from version i to i + 1 (``PRAGMA user_version``). Append, never
# edit: a database written by an older server is brought up to date on open by the scripts it has
# not seen yet, in one transaction.
_MIGRATIONS: tuple[str, ...] = (
    """
    CREATE TABLE results (
        id          INTEGER PRIMARY KEY AUTOINCREMENT,
        time        REAL    NOT NULL,           -- Unix seconds
        inspection  TEXT    NOT NULL,
        camera      TEXT    NOT NULL,
        passed      INTEGER NOT NULL,           -- 0 or 1
        data        TEXT    NOT NULL,           -- JSON object: measures or features
        duration_ms REAL    NOT NULL,
        config_hash TEXT    NOT NULL,
        request_id  INTEGER NOT NULL DEFAULT 0,
        peer        TEXT    NOT NULL DEFAULT '',
        error       TEXT,                       -- NULL unless the request failed
        image       TEXT,                       -- relative to the image directory, or NULL
        image_bytes INTEGER NOT NULL DEFAULT 0
    );
    CREATE INDEX results_by_time ON results (time);
    CREATE INDEX results_by_inspection ON results (inspection, time);
    -- The disk cap deletes the oldest images: find them without scanning rows that have none.
    CREATE INDEX results_with_image ON results (id) WHERE image IS NOT NULL;
    CREATE TABLE meta (key TEXT PRIMARY KEY, value TEXT NOT NULL);
    """,
    """
    -- The inspection's drawing over the input, stored beside it (image_bytes counts both files).
    ALTER TABLE results ADD COLUMN overlay TEXT;
    -- The console's filters read newest first (ORDER BY time DESC, id DESC: every index ends
    -- with the rowid, which is id): one index per filter, so that a page reads ~limit rows
    -- however large the log. The inspection index also covers the statistics' columns.
    DROP INDEX results_by_inspection;
    CREATE INDEX results_by_inspection ON results (inspection, time, passed, duration_ms);
    CREATE INDEX results_by_verdict ON results (passed, time);
    CREATE INDEX results_by_inspection_verdict ON results (inspection, passed, time);
    CREATE INDEX results_by_peer ON results (peer, time);
    """,
    """
    -- Who: the console user of a try, or the operator who answered the call about this
    -- failed result, with their choice, reason and time (Unix seconds). NULL: nobody.
    ALTER TABLE results ADD COLUMN operator TEXT;
    ALTER TABLE results ADD COLUMN operator_choice TEXT;
    ALTER TABLE results ADD COLUMN operator_reason TEXT;
    ALTER TABLE results ADD COLUMN operator_at REAL;
    -- The console's filter by operator reads newest first, as the others.
    CREATE INDEX results_by_operator ON results (operator, time);
    """,
)
SCHEMA_VERSION = len(_MIGRATIONS)

_IMAGE_NAME = re.compile(r"\d{4}-\d{2}-\d{2}/[0-9a-f]{32}\.png")


@dataclass(frozen=True)
class LogStatus:
    """Counters since the log was opened, for health reports.

    ``recorded`` counts rows written; ``failed`` rows that could not be written (their results
    were answered with ``stored: false``); ``failing`` whether the latest write failed.
    ``images_failed`` counts rows written without the image their policy asked for. ``errors``
    counts every fault (``failed`` + ``images_failed``); ``last_error`` is the latest fault's
    message and ``last_error_time`` its Unix time.
    """

    path: Path
    image_dir: Path
    store_images: ImagePolicy
    recorded: int
    errors: int
    last_error: str | None
    last_error_time: float | None
    failed: int
    failing: bool
    images_failed: int
    images_stored: int
    images_deleted: int
    images_skipped: int
    image_bytes: int
    max_image_bytes: int


def _access_error(path: Path, mode: int) -> OSError | None:
    """The error writing into (``mode`` with ``os.W_OK``) ``path`` would meet, or None.

    ``os.access`` answers for the real user, as the server will run; a read-only mount is told
    apart from missing permission so that the message names the true cause.
    """
    if os.access(path, mode):
        return None
    code = errno.EACCES
    with contextlib.suppress(OSError):
        if os.statvfs(path).f_flag & os.ST_RDONLY:
            code = errno.EROFS
    return OSError(code, os.strerror(code), str(path))


def _creatable_error(path: Path, *, directory: bool) -> OSError | None:
    """Why ``path`` (a file, or a ``directory``) could not be created or written, or None.

    Creates nothing: for ``check-config``, which must not leave files behind. SQLite also
    creates ``-wal`` and ``-shm`` files beside the database, so its directory must be writable
    even when the database file exists.
    """
    path = Path(os.path.abspath(path))
    if path.exists():
        if directory != path.is_dir():
            code = errno.ENOTDIR if directory else errno.EISDIR
            return OSError(code, os.strerror(code), str(path))
        if directory:
            return _access_error(path, os.W_OK | os.X_OK)
        return _access_error(path, os.R_OK | os.W_OK) or _access_error(
            path.parent, os.W_OK | os.X_OK
        )
    ancestor = path.parent
    # exists() is False both for a missing path and for one that runs through a file.
    while not ancestor.exists() and ancestor != ancestor.parent:
        ancestor = ancestor.parent
    if not ancestor.is_dir():
        return OSError(errno.ENOTDIR, os.strerror(errno.ENOTDIR), str(ancestor))
    return _access_error(ancestor, os.W_OK | os.X_OK)


def check_creatable(
    path: Path, *, store_images: ImagePolicy = "failures", image_dir: Path | None = None
) -> None:
    """Check, without creating anything, that a writer could open the log at ``path``.

    The database file (or the directories it needs) must be creatable and writable, and so must
    the image directory (default ``<db stem>-images/`` beside it) unless no images are stored.
    What is found is checked too: a directory where the database should be is refused, a file
    in the way of a directory as well.

    Raises
    ------
    ResultLogError
        Naming the path and the operating system's error, e.g. ``cannot create the result log
        /config/results.sqlite3: [Errno 30] Read-only file system: '/config'``.
    """
    path = Path(path)
    problem = _creatable_error(path, directory=False)
    if problem is None and store_images != "none":
        images = image_dir if image_dir is not None else path.with_name(f"{path.stem}-images")
        problem = _creatable_error(images, directory=True)
    if problem is not None:
        raise ResultLogError(f"cannot create the result log {path}: {problem}")


def _open_for_writing(path: Path) -> None:
    """Create the database file (and its directory) if needed, failing with the operating
    system's error: SQLite would only say "unable to open database file", and ``mkdir`` says
    "File exists" for a file in the way of a directory."""
    problem = _creatable_error(path, directory=False)
    if problem is not None:
        raise problem
    path.parent.mkdir(parents=True, exist_ok=True)
    os.close(os.open(path, os.O_RDWR | os.O_CREAT, 0o644))


def _connect(path: Path, *, readonly: bool, busy_timeout_s: float) -> sqlite3.Connection:
    """Open a connection in autocommit mode: transactions are explicit (``BEGIN IMMEDIATE``)."""
    if readonly:
        target, uri = path.resolve().as_uri() + "?mode=ro", True
    else:
        target, uri = str(path), False
    conn = sqlite3.connect(
        target, uri=uri, timeout=busy_timeout_s, isolation_level=None, check_same_thread=False
    )
    conn.execute(f"PRAGMA busy_timeout = {int(busy_timeout_s * 1000)}")
    return conn


def _statements(script: str) -> list[str]:
    """Split an SQL script into statements (``executescript`` would commit half-way)."""
    statements, pending = [], ""
    for piece in script.split(";"):
        pending += piece + ";"
        if sqlite3.complete_statement(pending):
            if pending.strip(" \n;"):
                statements.append(pending)
            pending = ""
    return statements


def _encode_png(image: np.ndarray) -> bytes:
    if not isinstance(image, np.ndarray) or image.ndim not in (2, 3) or image.size == 0:
        raise ValueError(f"image must be a non-empty (H, W) or (H, W, C) array, got {image!r:.80}")
    if image.ndim == 3 and image.shape[2] not in (1, 3, 4):
        raise ValueError(f"image must have 1, 3 or 4 channels, got shape {image.shape}")
    if image.dtype not in (np.uint8, np.uint16):
        raise ValueError(f"image must be uint8 or uint16, got {image.dtype}")
    ok, buf = cv2.imencode(".png", np.ascontiguousarray(image))
    if not ok:
        raise ValueError(f"PNG encoding failed for an image of shape {image.shape}")
    return bytes(buf)


def _write_atomically(path: Path, payload: bytes) -> None:
    """Write ``payload`` to ``path`` so that the file is either absent or complete."""
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.tmp")
    try:
        with open(tmp, "wb") as f:
            f.write(payload)
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(OSError):
            tmp.unlink()
        raise


class ResultLog:
    """The SQLite result log. Thread-safe; use it as a context manager or call :meth:`close`.

    Parameters
    ----------
    path : Path
        The database file; it and its directory are created when missing.
    store_images : {"none", "failures", "all"}
        Which input images to keep: none, those of failed inspections (and failed requests), all.
    image_dir : Path, optional
        Where the PNG files go; default ``<db stem>-images/`` beside the database.
    max_image_bytes : int
        Disk cap for the stored images; over it, the oldest images are deleted (see module doc).
    busy_timeout_s : float
        How long a write waits for a lock held by another connection before it counts as a fault.

    Raises
    ------
    ResultLogError
        The database cannot be created or opened, is not a result log, or was written by a newer
        cellvision. A server should not start without the log it was configured with.
    """

    ids_in_commit_order = True
    """One writer, ids assigned as rows commit (``ResultStore.ids_in_commit_order``)."""

    def __init__(
        self,
        path: Path,
        *,
        store_images: ImagePolicy = "failures",
        image_dir: Path | None = None,
        max_image_bytes: int = GIB,
        busy_timeout_s: float = 5.0,
        _readonly: bool = False,
    ) -> None:
        if store_images not in get_args(ImagePolicy):
            raise ValueError(
                f"store_images must be one of {get_args(ImagePolicy)}, got {store_images!r}"
            )
        if max_image_bytes < 0:
            raise ValueError(f"max_image_bytes must be >= 0, got {max_image_bytes}")
        self.path = Path(path)
        self.store_images: ImagePolicy = store_images
        self.max_image_bytes = max_image_bytes
        self.readonly = _readonly
        # Serialises the use of the connection (writes, queries, close).
        self._lock = threading.RLock()
        # The counters have their own lock, never held during I/O: the server reads them on its
        # event loop (PING), which must not wait for a write stuck on a locked database.
        self._stats = threading.Lock()
        self._closed = False
        self._recorded = 0
        self._failed = 0  # rows lost: their results went out with stored: false
        self._images_failed = 0
        self._errors = 0
        self._streak = 0  # consecutive failed records: log the first loudly, then quietly
        self._failing = False  # the latest record failed
        self._last_error: str | None = None
        self._last_error_time: float | None = None
        self._images_stored = 0
        self._images_deleted = 0
        self._images_skipped = 0
        self._image_bytes = 0
        try:
            if _readonly:
                if not self.path.is_file():
                    raise ResultLogError(f"no result log at {self.path}")
                self._conn = _connect(self.path, readonly=True, busy_timeout_s=busy_timeout_s)
                self._check_schema_readable()
            else:
                _open_for_writing(self.path)
                self._conn = _connect(self.path, readonly=False, busy_timeout_s=busy_timeout_s)
                self._prepare_for_writing()
            self.image_dir = self._resolve_image_dir(image_dir)
            if not _readonly:
                self._image_bytes = self._query_image_bytes()
                self._set_meta("image_dir", str(self.image_dir.resolve()))
                if store_images != "none":
                    self.image_dir.mkdir(parents=True, exist_ok=True)
                    self._remove_partial_images()
        except (sqlite3.Error, OSError) as exc:
            with contextlib.suppress(Exception):
                self._conn.close()
            raise ResultLogError(f"cannot open the result log {self.path}: {exc}") from exc
        except ResultLogError:
            with contextlib.suppress(Exception):
                self._conn.close()
            raise

    @classmethod
    def open_readonly(cls, path: Path, *, image_dir: Path | None = None) -> ResultLog:
        """A read-only view of an existing log, safe while a server writes to it.

        Creates nothing of its own (SQLite may add its ``-wal``/``-shm`` files beside the
        database); :meth:`record` raises :class:`ResultLogError`. ``image_dir`` defaults to the
        directory the writer recorded in the database.
        """
        return cls(Path(path), image_dir=image_dir, _readonly=True)

    # ------------------------------------------------------------------ opening

    def _prepare_for_writing(self) -> None:
        conn = self._conn
        mode = conn.execute("PRAGMA journal_mode = WAL").fetchone()[0]
        if str(mode).lower() != "wal":
            raise ResultLogError(f"{self.path}: cannot switch to WAL (journal mode {mode})")
        # NORMAL is enough against process crashes in WAL mode: see the module docstring.
        conn.execute("PRAGMA synchronous = NORMAL")
        # Keep the WAL file from staying huge after a burst once it has been checkpointed.
        conn.execute("PRAGMA journal_size_limit = 67108864")
        conn.execute("BEGIN IMMEDIATE")
        try:
            version = self._check_version()
            for script in _MIGRATIONS[version:]:
                for statement in _statements(script):
                    conn.execute(statement)
            conn.execute(f"PRAGMA user_version = {len(_MIGRATIONS)}")
            conn.execute("COMMIT")
        except BaseException:
            with contextlib.suppress(sqlite3.Error):
                conn.execute("ROLLBACK")
            raise

    def _check_version(self) -> int:
        version = int(self._conn.execute("PRAGMA user_version").fetchone()[0])
        if version > len(_MIGRATIONS):
            raise ResultLogError(
                f"{self.path} has result-log schema version {version}, newer than this "
                f"cellvision's {len(_MIGRATIONS)}: upgrade cellvision to use it"
            )
        if version == 0:
            tables = self._conn.execute(
                "SELECT count(*) FROM sqlite_master WHERE type = 'table'"
            ).fetchone()[0]
            if tables:
                raise ResultLogError(f"{self.path} is an SQLite database but not a result log")
        return version

    def _check_schema_readable(self) -> None:
        version = self._check_version()
        if version < len(_MIGRATIONS):
            what = "an empty database" if version == 0 else f"schema version {version}"
            raise ResultLogError(
                f"{self.path} is {what}; open it once with the server to create or upgrade it "
                f"to version {len(_MIGRATIONS)}"
            )

    def _resolve_image_dir(self, image_dir: Path | None) -> Path:
        if image_dir is not None:
            return Path(image_dir)
        if self.readonly:
            row = self._conn.execute("SELECT value FROM meta WHERE key = 'image_dir'").fetchone()
            if row is not None:
                return Path(row[0])
        return self.path.with_name(f"{self.path.stem}-images")

    def _set_meta(self, key: str, value: str) -> None:
        self._conn.execute(
            "INSERT INTO meta (key, value) VALUES (?, ?) "
            "ON CONFLICT (key) DO UPDATE SET value = excluded.value",
            (key, value),
        )

    def _remove_partial_images(self) -> None:
        # A writer killed between writing and renaming an image leaves a temporary file behind.
        for tmp in self.image_dir.glob("*/.*.png.tmp"):
            with contextlib.suppress(OSError):
                tmp.unlink()

    def _query_image_bytes(self) -> int:
        row = self._conn.execute(
            "SELECT coalesce(sum(image_bytes), 0) FROM results WHERE image IS NOT NULL"
        ).fetchone()
        return int(row[0])

    # ------------------------------------------------------------------ writing

    def record(self, entry: ResultEntry) -> int | None:
        """Store one result; return its id once it is committed, or ``None`` after a fault.

        Thread-safe. Never raises for runtime faults (full disk, I/O error, locked or read-only
        database, closed log): they are logged, counted (``failed`` in :meth:`status`, which
        turns :meth:`health` not ok), and the next call tries again. ``None`` means the row is
        not in the log: the caller must say so to whoever gets the result (``stored: false``).
        Raises :class:`ResultLogError` only on a read-only view (a programming error).
        """
        if self.readonly:
            raise ResultLogError(f"{self.path} was opened read-only: it cannot record results")
        # Any fault of the log, even a bug or a strange entry, must not fail the inspection:
        # hence the broad excepts. Slow work (JSON, PNG, file) happens outside the lock.
        try:
            if self._closed:
                raise ResultLogError("the result log is closed")
            values = row_values(entry)
        except Exception as exc:
            self._fault(f"result of {entry.inspection!r} not recorded", exc, row_lost=True)
            return None
        try:
            image_name, image_bytes = self._store_image(entry)
        except Exception as exc:
            self._fault(f"image of {entry.inspection!r} not stored", exc, row_lost=False)
            image_name, image_bytes = None, 0
        overlay_name = None
        if image_name is not None and entry.overlay is not None:
            try:
                overlay_name, overlay_bytes = self._store_overlay(entry, image_bytes)
            except Exception as exc:
                self._fault(f"overlay of {entry.inspection!r} not stored", exc, row_lost=False)
                overlay_name, overlay_bytes = None, 0
            image_bytes += overlay_bytes
        with self._lock:
            try:
                if self._closed:
                    raise ResultLogError("the result log is closed")
                new_id, pruned = self._insert(
                    (*values, entry.operator or None), image_name, overlay_name, image_bytes
                )
            except Exception as exc:
                for name in (image_name, overlay_name):
                    if name is not None:
                        self._unlink(name)
                self._fault(f"result of {entry.inspection!r} not recorded", exc, row_lost=True)
                return None
            with self._stats:
                self._recorded += 1
                self._failing = False
                if image_name is not None:
                    self._images_stored += 1
                    self._image_bytes += image_bytes
                for _, size in pruned:
                    self._image_bytes -= size
                self._images_deleted += len(pruned)
                streak, self._streak = self._streak, 0
            if streak:
                logger.warning("result log %s recovered after %d faults", self.path, streak)
        for names, _ in pruned:
            for name in names:
                if name is not None:
                    self._unlink(name)
        return new_id

    @property
    def keeps_images(self) -> bool:
        """Whether any image is ever stored: then the server has overlays drawn for the log."""
        return self.store_images != "none"

    def _wants_image(self, entry: ResultEntry) -> bool:
        if entry.image is None or self.store_images == "none":
            return False
        return self.store_images == "all" or not entry.passed or entry.error is not None

    def _store_image(self, entry: ResultEntry) -> tuple[str | None, int]:
        """Encode and write the image if the policy wants it; return its name and size."""
        if not self._wants_image(entry):
            return None, 0
        assert entry.image is not None
        payload = _encode_png(entry.image)
        if len(payload) > self.max_image_bytes:
            with self._stats:
                self._images_skipped += 1
            logger.debug("image of %d bytes is larger than the whole cap", len(payload))
            return None, 0
        return self._write_image(entry.time, payload), len(payload)

    def _store_overlay(self, entry: ResultEntry, input_bytes: int) -> tuple[str | None, int]:
        """Encode and write the overlay beside a stored input; skipped when the two would not
        fit the cap together (the input matters more: a try can re-run on it)."""
        assert entry.overlay is not None
        payload = _encode_png(entry.overlay)
        if input_bytes + len(payload) > self.max_image_bytes:
            with self._stats:
                self._images_skipped += 1
            return None, 0
        return self._write_image(entry.time, payload), len(payload)

    def _write_image(self, t: float, payload: bytes) -> str:
        day = datetime.fromtimestamp(t, UTC).strftime("%Y-%m-%d")
        name = f"{day}/{uuid.uuid4().hex}.png"
        _write_atomically(self.image_dir / name, payload)
        return name

    def _insert(
        self,
        values: tuple[Any, ...],
        image_name: str | None,
        overlay_name: str | None,
        image_bytes: int,
    ) -> tuple[int, list[tuple[tuple[str | None, str | None], int]]]:
        """Insert the row (``values``: :func:`row_values` and the operator) and drop the oldest
        images over the cap, in one transaction."""
        conn = self._conn
        conn.execute("BEGIN IMMEDIATE")
        try:
            cursor = conn.execute(
                "INSERT INTO results (time, inspection, camera, passed, data, duration_ms, "
                "config_hash, request_id, peer, error, operator, image, overlay, image_bytes) "
                "VALUES (?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?)",
                (*values, image_name, overlay_name, image_bytes),
            )
            new_id = cursor.lastrowid
            assert new_id is not None
            pruned = self._prune(self._image_bytes + image_bytes, keep=new_id)
            conn.execute("COMMIT")
        except BaseException:
            with contextlib.suppress(sqlite3.Error):
                conn.execute("ROLLBACK")
            raise
        return new_id, pruned

    def _prune(self, total: int, *, keep: int) -> list[tuple[tuple[str | None, str | None], int]]:
        """Null the image and overlay references of the oldest rows until ``total`` fits the cap.

        Returns the ((image, overlay) names, bytes) of the files to delete once the transaction
        is committed: a crash in between leaves an unreferenced file (harmless), never a row
        pointing at nothing.
        """
        pruned: list[tuple[tuple[str | None, str | None], int]] = []
        while total > self.max_image_bytes:
            rows = self._conn.execute(
                "SELECT id, image, overlay, image_bytes FROM results "
                "WHERE image IS NOT NULL AND id != ? ORDER BY id LIMIT 64",
                (keep,),
            ).fetchall()
            if not rows:
                break
            for row_id, name, overlay, size in rows:
                if total <= self.max_image_bytes:
                    break
                self._conn.execute(
                    "UPDATE results SET image = NULL, overlay = NULL, image_bytes = 0 WHERE id = ?",
                    (row_id,),
                )
                pruned.append(((name, overlay), int(size)))
                total -= int(size)
        return pruned

    def _unlink(self, name: str) -> None:
        path = self._image_path(name)
        if path is None:
            return
        try:
            path.unlink(missing_ok=True)
        except OSError as exc:
            logger.warning("cannot delete the stored image %s: %s", path, exc)

    def _image_path(self, name: str | None) -> Path | None:
        # The name comes from our own database, but a copied or edited file must not make us
        # open or delete anything outside the image directory.
        if name is None or not _IMAGE_NAME.fullmatch(name):
            return None
        return self.image_dir / name

    def _fault(self, what: str, exc: BaseException, *, row_lost: bool) -> None:
        message = f"{what}: {exc}"
        if isinstance(exc, OSError) and exc.errno == errno.ENOSPC:
            message += " (disk full)"
        elif isinstance(exc, sqlite3.Error) and getattr(exc, "sqlite_errorname", None):
            # "disk I/O error" alone does not tell a full disk (EFBIG, ENOSPC) from a bad one.
            message += f" ({exc.sqlite_errorname})"
        with self._stats:
            if row_lost:
                self._failed += 1
                self._failing = True
            else:
                self._images_failed += 1
            self._errors += 1
            self._streak += 1
            first = self._streak == 1
            self._last_error = message
            self._last_error_time = time.time()
        if first:
            logger.error("result log %s: %s", self.path, message)
        else:
            logger.debug("result log %s: %s", self.path, message)

    # ------------------------------------------------------------------ reading

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
        """Results with ``time >= since`` (Unix seconds), of one inspection, with one verdict,
        from peers starting with ``peer``, annotated with ``operator``, that come after row
        ``before_id`` in the order asked (paging: the rows older than it, newest first); at
        most ``limit`` of them, newest (or oldest) first, by time and then id.

        Every filter is served by an index (see the migrations), so a page costs about ``limit``
        rows read whatever the log's size; the tests check the query plans.
        """
        sql, params = self.query_sql(
            since=since,
            inspection=inspection,
            passed=passed,
            limit=limit,
            newest_first=newest_first,
            peer=peer,
            before_id=before_id,
            operator=operator,
        )
        with self._lock:
            self._check_open()
            rows = self._conn.execute(sql, params).fetchall()
        return [self._row(row) for row in rows]

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
        """The SQL and parameters :meth:`query` runs (for ``EXPLAIN QUERY PLAN`` and the bench)."""
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
            mark="?",
            boolean=int,
        )

    def _key_of(self, row_id: int) -> tuple[float, int] | None:
        with self._lock:
            self._check_open()
            key = self._conn.execute(
                "SELECT time, id FROM results WHERE id = ?", (row_id,)
            ).fetchone()
        return None if key is None else (float(key[0]), int(key[1]))

    def timings(
        self, *, inspection: str, since: float
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The time (Unix seconds), verdict (bool) and duration (ms) of every production result
        of ``inspection`` with ``time >= since`` (console tries left out), oldest first: what
        statistics are made of.

        Read from one covering index, without parsing any row's data, so that a window of
        100,000 results costs tens of milliseconds.
        """
        rows = self.timing_rows(inspection=inspection, since=since)
        return rows.times, rows.passed, rows.durations

    def timing_rows(
        self, *, inspection: str, since: float | None = None, after_id: int | None = None
    ) -> TimingRows:
        """``inspection``'s production rows with ``time >= since`` (oldest first) or, with
        ``after_id``, those written after that row (by id: what a cache of statistics adds),
        with the log's last row id when read (:class:`TimingRows`)."""
        with self._lock:
            self._check_open()
            upto = self._conn.execute("SELECT coalesce(max(id), 0) FROM results").fetchone()[0]
            sql, params = timing_sql(
                inspection, since=since, after_id=after_id, upto_id=upto, mark="?", boolean=int
            )
            rows = self._conn.execute(sql, params).fetchall()
        return TimingRows.of(rows, int(upto))

    def count(
        self,
        *,
        since: float | None = None,
        inspection: str | None = None,
        passed: bool | None = None,
    ) -> int:
        """How many results match the filters (all of them without filters)."""
        where, params = _where(since, inspection, passed, mark="?", boolean=int)
        with self._lock:
            self._check_open()
            return int(
                self._conn.execute(f"SELECT count(*) FROM results{where}", params).fetchone()[0]
            )

    def get(self, row_id: int) -> StoredResult | None:
        """The result with id ``row_id``, or None."""
        if not is_row_id(row_id):
            return None
        with self._lock:
            self._check_open()
            row = self._conn.execute(
                f"SELECT {COLUMNS} FROM results WHERE id = ?", (int(row_id),)
            ).fetchone()
        return None if row is None else self._row(row)

    def _row(self, row: tuple[Any, ...]) -> StoredResult:
        (row_id, t, inspection, camera, passed, data, duration, chash, rid, peer, error, image) = (
            row[:12]
        )
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
            image_path=self._image_path(image),
            overlay_path=self._image_path(row[12]),
            operator=OperatorMark.from_columns(*row[OPERATOR_COLUMNS]),
        )

    def annotate(self, row_id: int, *, name: str, choice: str, reason: str, at: float) -> bool:
        """Write an operator's answer onto row ``row_id`` (the failed result the call was
        about): their ``name``, ``choice``, ``reason`` ("" for none) and when (``at``, Unix
        seconds). False when there is no such row; ResultLogError when it cannot be written."""
        if not is_row_id(row_id):
            return False
        if self.readonly:
            raise ResultLogError(f"{self.path} was opened read-only: it cannot annotate results")
        with self._lock:
            self._check_open()
            try:
                cursor = self._conn.execute(
                    "UPDATE results SET operator = ?, operator_choice = ?, operator_reason = ?, "
                    "operator_at = ? WHERE id = ?",
                    (str(name), str(choice), str(reason) or None, float(at), int(row_id)),
                )
            except sqlite3.Error as exc:
                raise ResultLogError(f"cannot annotate result {row_id}: {exc}") from exc
        return cursor.rowcount > 0

    def _check_open(self) -> None:
        if self._closed:
            raise ResultLogError(f"the result log {self.path} is closed")

    # ------------------------------------------------------------------ status and lifetime

    @property
    def errors(self) -> int:
        """Faults since the log was opened (see :class:`LogStatus`)."""
        return self._errors

    def status(self) -> LogStatus:
        """The counters; never waits for a write in progress."""
        with self._stats:
            return LogStatus(
                path=self.path,
                image_dir=self.image_dir,
                store_images=self.store_images,
                recorded=self._recorded,
                errors=self._errors,
                last_error=self._last_error,
                last_error_time=self._last_error_time,
                failed=self._failed,
                failing=self._failing,
                images_failed=self._images_failed,
                images_stored=self._images_stored,
                images_deleted=self._images_deleted,
                images_skipped=self._images_skipped,
                image_bytes=self._image_bytes,
                max_image_bytes=self.max_image_bytes,
            )

    def health(self) -> dict[str, Any]:
        """The log's part of the server's health report (PONG ``health.result_log``, SPEC §5.5).

        ``ok`` is false once a row could not be written since the log was opened (sticky, see
        the module doc); ``written`` and ``failed`` count rows, ``failing`` says whether the
        latest write failed, ``images_failed`` counts rows written without their image, and
        ``last_error``/``last_error_time`` (Unix seconds) describe the latest fault.
        """
        status = self.status()
        return {
            "ok": status.failed == 0,
            "written": status.recorded,
            "failed": status.failed,
            "failing": status.failing,
            "images_failed": status.images_failed,
            "last_error": status.last_error,
            "last_error_time": status.last_error_time,
        }

    def close(self) -> None:
        """Close the database; later :meth:`record` calls return ``None``. Idempotent."""
        with self._lock:
            if self._closed:
                return
            self._closed = True
            try:
                self._conn.close()
            except sqlite3.Error as exc:
                logger.warning("closing the result log %s: %s", self.path, exc)

    def __enter__(self) -> ResultLog:
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        self.close()
