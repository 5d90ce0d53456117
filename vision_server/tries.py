"""Console tries in the result log: how a try is told apart from a production result.

The rule (docs/console.md, "Tries in the result log"): a console try is recorded, so that the
Results page can reopen it, but only as a try. Its row's ``peer`` starts with
:data:`TRY_PEER_PREFIX` and its ``data`` holds the options it ran with under ``"try"``; every
place that shows results marks it as a try, and no production figure counts it (``/api/stats``,
the Prometheus counters). A try with a wrong option can pass a failing part: counted as a
production pass, it would lie about the line.

The service builds the log's row in a worker and does not know about options as such; the HTTP
front-end announces a try's options here (keyed by its peer and request id, unique per try)
before the run and withdraws them after, and :func:`marked_data` (called by both stores through
``row_values``) adds them to the row.
"""

from __future__ import annotations

import itertools
import threading
from collections.abc import Mapping
from typing import Any

__all__ = ["TRY_PEER_PREFIX", "announce", "is_try", "marked_data", "next_request_id", "withdraw"]

TRY_PEER_PREFIX = "console "
"""The peer of every console try: ``console host:port`` (a prefix the peer filter accepts)."""

_lock = threading.Lock()
_pending: dict[tuple[str, int], dict[str, Any]] = {}
_ids = itertools.count(1)


def is_try(peer: str) -> bool:
    """Whether a result with this peer is a console try."""
    return peer.startswith(TRY_PEER_PREFIX)


def next_request_id() -> int:
    """A request id no other try of this process has (the key of its announced options)."""
    with _lock:
        return next(_ids)


def announce(peer: str, request_id: int, options: Mapping[str, Any]) -> None:
    """The options try ``(peer, request_id)`` runs with, until :func:`withdraw`."""
    with _lock:
        _pending[(peer, request_id)] = dict(options)


def withdraw(peer: str, request_id: int) -> None:
    """Forget a try's options once it has been answered (or refused)."""
    with _lock:
        _pending.pop((peer, request_id), None)


def marked_data(peer: str, request_id: int, data: Mapping[str, Any]) -> Mapping[str, Any]:
    """The ``data`` a row stores: a try's gets ``"try": {"options": {...}}`` (empty options
    when it ran the configuration as written); any other row's is returned as given."""
    if not is_try(peer):
        return data
    with _lock:
        options = dict(_pending.get((peer, request_id), {}))
    return {**data, "try": {"options": options}}
