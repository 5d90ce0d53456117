"""What every result log is: the records it takes, the rows it gives back, and the interface the
server, the console and ``vision-server results`` use without knowing where the rows live.

Two implementations: :class:`.sqlite.ResultLog` (SQLite on the cell PC, images on its disk)
and :class:`.postgres.PgResultLog` (PostgreSQL, one history for a plant, with a local spool for
when the database is down). :func:`.configured.open_result_store` picks one from the
configuration.
"""

from __future__ import annotations

import json
import math
from collections.abc import Mapping
from dataclasses import dataclass, field
from datetime import UTC, datetime
from pathlib import Path
from types import TracebackType
from typing import Any, Literal, Protocol

import numpy as np

from . import tries

__all__ = [
    "ImagePolicy",
    "OperatorMark",
    "ResultEntry",
    "ResultLogError",
    "ResultStore",
    "StoredResult",
    "data_json",
    "parse_data",
    "row_values",
]

ImagePolicy = Literal["none", "failures", "all"]


MAX_ROW_ID = 2**63 - 1
"""The largest id a row may have (SQLite's and PostgreSQL's 64-bit integers): an id beyond,
from a client, names no row (it is not sent to the database, which refuses it)."""


def is_row_id(value: object) -> bool:
    """Whether ``value`` may be a row's id: an integer in 1..:data:`MAX_ROW_ID`."""
    return isinstance(value, int) and not isinstance(value, bool) and 1 <= value <= MAX_ROW_ID


class ResultLogError(Exception):
    """The result log cannot be opened or used as asked (not its runtime faults: those are
    counted, see :meth:`ResultStore.record`)."""


@dataclass(frozen=True)
class ResultEntry:
    """One answered inspection, as the server hands it to :meth:`ResultStore.record`.

    ``time`` in Unix seconds; ``duration_ms`` in milliseconds; ``data`` JSON-able (numpy scalars
    and arrays are converted); ``image`` the input image, ``(H, W, 3)`` BGR or ``(H, W)`` grey,
    uint8 or uint16, stored according to the log's policy; ``overlay`` the inspection's drawing
    (same kinds of array), stored with the input when the input is stored.
    """

    time: float
    inspection: str
    camera: str
    passed: bool
    data: Mapping[str, Any]
    duration_ms: float
    config_hash: str
    request_id: int = 0
    peer: str = ""
    image: np.ndarray | None = field(default=None, repr=False, compare=False)
    error: str | None = None
    overlay: np.ndarray | None = field(default=None, repr=False, compare=False)
    options: Mapping[str, Any] = field(default_factory=dict)
    """The request's own parameters (SPEC §6.3) the inspection ran with; stored with a
    console try's row (:mod:`vision_server.results.tries`)."""
    config: Mapping[str, Any] | None = None
    """The whole inspection mapping a console try ran instead of the configured inspection
    (an edited or a new one); stored with the try's row under ``data.try.config``."""
    operator: str = ""
    """Who asked, when a person did (a console try's signed-in user); "" for a robot's."""


@dataclass(frozen=True)
class OperatorMark:
    """The person a row is annotated with: a console try's user (``choice`` None), or the
    operator who answered the call about this failed result, with their ``choice``, ``reason``
    ("" when none) and when (``at``, Unix seconds)."""

    name: str
    choice: str | None = None
    reason: str | None = None
    at: float | None = None

    def to_json(self) -> dict[str, Any]:
        return {"name": self.name, "choice": self.choice, "reason": self.reason, "at": self.at}

    @classmethod
    def from_columns(cls, name: Any, choice: Any, reason: Any, at: Any) -> OperatorMark | None:
        """The mark of a row's four operator columns (None when it has none)."""
        if not name:
            return None
        return cls(
            str(name),
            None if choice is None else str(choice),
            None if reason is None else str(reason),
            None if at is None else float(at),
        )


@dataclass(frozen=True)
class StoredResult:
    """One row of the log. ``image_path`` is ``None`` when no image was stored or it was deleted
    by the disk cap (the file may also have been removed by hand: check before opening);
    ``overlay_path`` likewise for the drawn overlay, which also is ``None`` when the inspection
    drew none (a failed request) or the row predates stored overlays."""

    id: int
    time: float
    inspection: str
    camera: str
    passed: bool
    data: dict[str, Any]
    duration_ms: float
    config_hash: str
    request_id: int
    peer: str
    error: str | None
    image_path: Path | None
    overlay_path: Path | None = None
    operator: OperatorMark | None = None
    """Who this row is annotated with (an operator's answer, a try's user), or None."""

    @property
    def is_try(self) -> bool:
        """Whether this row is a console try (see :mod:`vision_server.results.tries`)."""
        return tries.is_try(self.peer)

    def to_json(self) -> dict[str, Any]:
        """A JSON-able dict (``time`` as Unix seconds and as ISO 8601 UTC, ``verdict``)."""
        return {
            "id": self.id,
            "time": self.time,
            "time_iso": datetime.fromtimestamp(self.time, UTC).isoformat(timespec="milliseconds"),
            "inspection": self.inspection,
            "camera": self.camera,
            "verdict": "pass" if self.passed else "fail",
            "data": self.data,
            "duration_ms": self.duration_ms,
            "config_hash": self.config_hash,
            "request_id": self.request_id,
            "peer": self.peer,
            "try": self.is_try,
            "error": self.error,
            "image_path": str(self.image_path) if self.image_path is not None else None,
            "overlay_path": str(self.overlay_path) if self.overlay_path is not None else None,
            "operator": None if self.operator is None else self.operator.to_json(),
        }


@dataclass(frozen=True)
class TimingRows:
    """Production rows of one inspection as statistics read them: ``ids``, ``times`` (Unix
    seconds), ``passed`` (bool) and ``durations`` (ms), in the order asked; ``upto``, the
    log's last row id when they were read (no row after it is among them)."""

    ids: np.ndarray
    times: np.ndarray
    passed: np.ndarray
    durations: np.ndarray
    upto: int

    @classmethod
    def of(cls, rows: list[tuple[Any, ...]], upto: int) -> TimingRows:
        table = np.array(rows, dtype=float).reshape(-1, 4)
        return cls(table[:, 0].astype(np.int64), table[:, 1], table[:, 2] != 0, table[:, 3], upto)


class ResultStore(Protocol):
    """The interface of a result log, whatever keeps its rows.

    ``record`` is called from the server's worker threads before the answer is sent; it never
    raises for runtime faults and returns ``None`` when the row is lost (the answer then says
    ``stored: false``), otherwise an int: the row's id, or 0 when the row is durably kept
    elsewhere first and gets its id later (PostgreSQL's spool). The readers raise
    :class:`ResultLogError` when the rows cannot be read (a closed log, a database that is down).
    ``annotate`` writes an operator's answer onto a row (False when there is no such row;
    ResultLogError when the log cannot be written); ``query(operator=NAME)`` reads the rows
    annotated with NAME through an index.
    """

    ids_in_commit_order: bool
    """Whether a row written later always has a larger id (one writer: SQLite), so that the
    rows after an id are all the rows written since it was read (:class:`TimingsCache`)."""

    @property
    def keeps_images(self) -> bool: ...

    @property
    def errors(self) -> int: ...

    def record(self, entry: ResultEntry) -> int | None: ...

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
    ) -> list[StoredResult]: ...

    def annotate(self, row_id: int, *, name: str, choice: str, reason: str, at: float) -> bool: ...

    def timings(
        self, *, inspection: str, since: float
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]: ...

    def timing_rows(
        self, *, inspection: str, since: float | None = None, after_id: int | None = None
    ) -> TimingRows: ...

    def count(
        self,
        *,
        since: float | None = None,
        inspection: str | None = None,
        passed: bool | None = None,
    ) -> int: ...

    def get(self, row_id: int) -> StoredResult | None: ...

    def health(self) -> dict[str, Any]: ...

    def close(self) -> None: ...

    def __enter__(self) -> ResultStore: ...

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None: ...


def _json_default(value: Any) -> Any:
    if isinstance(value, np.ndarray | np.generic):
        return value.tolist()
    if isinstance(value, Path):
        return str(value)
    if isinstance(value, set | frozenset | tuple):
        return list(value)
    return repr(value)


def data_json(data: Mapping[str, Any]) -> str:
    """The measures as JSON text. NaN and infinities are written as JSON's common extension
    (NaN, Infinity), which json.loads reads back: a measure that failed to converge is still
    worth keeping (and is why the column is text, not PostgreSQL's jsonb)."""
    return json.dumps(dict(data), default=_json_default, separators=(",", ":"))


def parse_data(text: str) -> dict[str, Any]:
    """A row's ``data`` column back as a dict (a damaged value is kept, not dropped)."""
    try:
        parsed = json.loads(text)
    except ValueError:
        return {"_unparsed": text}
    return parsed if isinstance(parsed, dict) else {"_value": parsed}


def row_values(entry: ResultEntry) -> tuple[Any, ...]:
    """The entry's columns ``time`` to ``error``, checked and converted (``passed`` as bool)."""
    if not math.isfinite(entry.time):
        raise ValueError(f"time must be a finite Unix time, got {entry.time}")
    return (
        float(entry.time),
        str(entry.inspection),
        str(entry.camera),
        bool(entry.passed),
        data_json(tries.marked_data(str(entry.peer), entry.options, entry.data, entry.config)),
        float(entry.duration_ms),
        str(entry.config_hash),
        int(entry.request_id),
        str(entry.peer),
        None if entry.error is None else str(entry.error),
    )
