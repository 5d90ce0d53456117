"""The result log: every answered inspection, kept where the configuration says.

- :mod:`.store`: what every log is (:class:`ResultStore`), the record it takes
  (:class:`ResultEntry`) and the rows it gives back (:class:`StoredResult`).
- :mod:`.sqlite`: :class:`ResultLog`, the cell's own log (SQLite, images of failures on disk).
- :mod:`.postgres`: :class:`PgResultLog`, one history for a plant (PostgreSQL), with
  :mod:`.spool` keeping rows on local disk while the database is down and
  :mod:`.postgres_schema` its versioned schema.
- :mod:`.query`: the filters and pages both stores share.
- :mod:`.scan`: an inspection's newest production rows, a page at a time.
- :mod:`.tries`: how a console try is marked, so that no reader counts it as production.
- :mod:`.configured`: the configured store opened, for writing or for reading.
- :mod:`.timings_cache`: the statistics' columns, read once and then only the rows since.
"""

from .configured import check_result_store, open_readonly, open_result_store
from .postgres import PgResultLog, is_database_url, redact_url
from .scan import ProductionRows
from .sqlite import ResultLog
from .store import (
    MAX_ROW_ID,
    ResultEntry,
    ResultLogError,
    ResultStore,
    StoredResult,
    TimingRows,
    is_row_id,
)
from .timings_cache import TimingsCache
from .tries import TRY_PEER_PREFIX, is_try

__all__ = [
    "MAX_ROW_ID",
    "is_row_id",
    "TRY_PEER_PREFIX",
    "PgResultLog",
    "ProductionRows",
    "ResultEntry",
    "ResultLog",
    "ResultLogError",
    "ResultStore",
    "StoredResult",
    "TimingRows",
    "TimingsCache",
    "check_result_store",
    "is_database_url",
    "is_try",
    "open_readonly",
    "open_result_store",
    "redact_url",
]
