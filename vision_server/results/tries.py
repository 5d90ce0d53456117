"""Console tries in the result log: how a try is told apart from a production result.

The rule (docs/console.md, "Tries in the result log"): a console try is recorded, so that the
Results page can reopen it, but only as a try. Its row's ``peer`` starts with
:data:`TRY_PEER_PREFIX` and its ``data`` holds the options it ran with under ``"try"``; every
place that shows results marks it as a try, and no production figure counts it (``/api/stats``,
the Prometheus counters). A try with a wrong option can pass a failing part: counted as a
production pass, it would lie about the line.

The service hands the log each request's options with its row (``ResultEntry.options``);
:func:`marked_data` (called by both stores through ``row_values``) keeps a try's under
``"try"``.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

__all__ = ["TRY_PEER_PREFIX", "is_try", "marked_data"]

TRY_PEER_PREFIX = "console "
"""The peer of every console try: ``console host:port`` (a prefix the peer filter accepts)."""


def is_try(peer: str) -> bool:
    """Whether a result with this peer is a console try."""
    return peer.startswith(TRY_PEER_PREFIX)


def marked_data(
    peer: str,
    options: Mapping[str, Any],
    data: Mapping[str, Any],
    config: Mapping[str, Any] | None = None,
) -> Mapping[str, Any]:
    """The ``data`` a row stores: a try's gets ``"try": {"options": {...}}`` (the options it ran
    with; empty when it ran the configuration as written), and ``"config"`` beside them when
    it ran a whole edited or new inspection mapping instead; any other row's is returned as
    given."""
    if not is_try(peer):
        return data
    marked: dict[str, Any] = {"options": dict(options)}
    if config is not None:
        marked["config"] = dict(config)
    return {**data, "try": marked}
