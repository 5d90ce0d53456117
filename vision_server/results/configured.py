"""Open the configured result log, SQLite or PostgreSQL, behind the one :class:`ResultStore`
interface (the server, the console and ``vision-server results`` never ask which)."""

from __future__ import annotations

from pathlib import Path

from ..config import ResultsConfig
from .postgres import PgResultLog, is_database_url
from .sqlite import ResultLog, check_creatable
from .store import ResultStore

__all__ = ["check_result_store", "open_readonly", "open_result_store"]


def open_result_store(settings: ResultsConfig) -> ResultStore | None:
    """The configured log opened for writing, or None when it is off.

    Raises :class:`~vision_server.results.store.ResultLogError` naming the cause.
    """
    if settings.url is not None:
        assert settings.spool is not None
        return PgResultLog(settings.url, spool=settings.spool)
    if settings.path is None:
        return None
    return ResultLog(
        settings.path,
        store_images=settings.store_images,  # type: ignore[arg-type]
        max_image_bytes=settings.max_image_bytes,
    )


def check_result_store(settings: ResultsConfig) -> None:
    """Check, creating nothing and connecting nowhere, that the log could be opened: the SQLite
    file's directory is writable; the PostgreSQL spool's likewise (the URL was checked when the
    configuration was read; whether the database answers is a runtime matter, spooled)."""
    if settings.url is not None:
        assert settings.spool is not None
        check_creatable(settings.spool, store_images="none")
    elif settings.path is not None:
        check_creatable(
            settings.path,
            store_images=settings.store_images,  # type: ignore[arg-type]
        )


def open_readonly(target: str | Path) -> ResultStore:
    """A read-only view of an SQLite file or a PostgreSQL URL (``vision-server results``)."""
    if is_database_url(target):
        return PgResultLog.open_readonly(str(target))
    return ResultLog.open_readonly(Path(target))
