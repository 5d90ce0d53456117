"""The server's operating-system process: what it starts with and how its threads yield.

- :mod:`.decoder_limits`: OpenCV's image-size limits, set before cv2 loads (importing
  :mod:`vision_server` installs the default) and re-executed into by ``serve``.
- :mod:`.malloc`: the glibc malloc settings ``serve`` starts with (:data:`PROCESS_ENV`).
- :mod:`.cpu_priority`: the niceness of the work that can wait (the main lane's threads, the
  worker processes, the console's live view).
- :mod:`.event_loop`: the event loop ``serve`` runs on (asyncio's or uvloop).
- :mod:`.ownership`: files one running server owns (a spool, a certificate store), claimed
  with a lock so that two servers never share them.

Nothing here imports cv2 or another room of the server: every room may use it, and
:mod:`vision_server` imports it first.
"""

from . import decoder_limits
from .cpu_priority import (
    MAX_NICE,
    POLICIES,
    lower_this_thread,
    run_this_process_at,
    target_niceness,
)
from .event_loop import EVENT_LOOPS, loop_factory, uvloop_available
from .malloc import PROCESS_ENV
from .ownership import Claim, Claimed, claim

__all__ = [
    "EVENT_LOOPS",
    "Claim",
    "Claimed",
    "MAX_NICE",
    "POLICIES",
    "PROCESS_ENV",
    "claim",
    "decoder_limits",
    "loop_factory",
    "lower_this_thread",
    "run_this_process_at",
    "target_niceness",
    "uvloop_available",
]
