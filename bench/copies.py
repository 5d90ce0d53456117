"""Copies of the image per INSPECT, counted by the project's buffer-tracking helper
(``count_copies(width, height)`` in tests/helpers/copies.py: one INSPECT with an overlay over
loopback, every buffer handed to a transport or copied into a frame body tracked). Without it
the figure is "not measured": copies are counted by tracking buffers, never guessed from timing.
"""

from __future__ import annotations

import importlib
import inspect
import sys
from collections.abc import Callable, Mapping
from typing import Any

from .common import ROOT

PLACES = ("copies", "wireio")
"""Where ``count_copies`` may live, searched in this order."""


def find_count_copies() -> tuple[Callable[..., Any] | None, str]:
    """``count_copies`` and the module it came from, or None and where it was looked for."""
    helpers = str(ROOT / "tests" / "helpers")
    if helpers not in sys.path:
        sys.path.append(helpers)  # the tests' helpers are modules of their own there
    for place in PLACES:
        try:
            module = importlib.import_module(place)
        except ImportError:
            continue
        found = getattr(module, "count_copies", None)
        if callable(found):
            return found, place
    return None, ", ".join(PLACES)


def _render(counted: Any) -> str | None:
    if hasattr(counted, "server_copies") and hasattr(counted, "client_copies"):
        return f"server {counted.server_copies:.3f}, client {counted.client_copies:.3f}"
    if isinstance(counted, bool):
        return None
    if isinstance(counted, int | float):
        return f"{counted:g}"
    if isinstance(counted, Mapping) and all(
        isinstance(v, int | float) and not isinstance(v, bool) for v in counted.values()
    ):
        return ", ".join(f"{k} {v:g}" for k, v in counted.items())
    return None


NOT_MEASURED = "not measured"


def copies_per_request(image: Any) -> tuple[str, str]:
    """(the copies of ``image`` one INSPECT makes, as the helper counts them, or "not
    measured"; where the figure comes from, or why there is none). The helper is called as
    ``count_copies(width, height)`` for ``image``'s size and answers full-image copies per
    side (``server_copies``, ``client_copies``), a number or a mapping of numbers."""
    count_copies, where = find_count_copies()
    if count_copies is None:
        return NOT_MEASURED, f"there is no buffer-tracking helper (no count_copies in {where})"
    shape = getattr(image, "shape", None)
    if shape is None or len(shape) < 2:
        return NOT_MEASURED, f"no image size to count copies for ({image!r:.40})"
    try:
        shown = _render(count_copies(int(shape[1]), int(shape[0])))
    except TypeError as exc:
        signature = _signature(count_copies)
        return NOT_MEASURED, (
            f"count_copies{signature} in {where} is not called as count_copies(width, "
            f"height): {exc}"
        )
    if shown is None:
        return NOT_MEASURED, f"count_copies in {where} answered something else than counts"
    return shown, f"counted by count_copies in {where}"


def _signature(fn: Callable[..., Any]) -> str:
    try:
        return str(inspect.signature(fn))
    except (TypeError, ValueError):
        return "(...)"
