"""Fewer malloc arenas for the server process (glibc): ``MALLOC_ARENA_MAX``.

glibc gives each thread that allocates under contention an arena of its own (up to 8 per core)
and rarely returns an arena's freed memory to the system. The server's threads (the event loop,
the workers of both lanes, the result log's writer) each allocate and free request bodies of up
to ``max_frame_bytes``. Measured with the hostile-frame soak (scripts/soak.py, 1,000 frames),
the server's peak RSS ranged from 204 to 497 MiB over 9 runs with glibc's default, and from
237 to 327 MiB over 3 runs started with two arenas (the soak's bound: 416 MiB).

glibc reads the limit when the process starts (``mallopt`` later, once threads have allocated,
was measured to change nothing), so ``vision-server serve`` starts itself again with it when it
is not set, with OpenCV's limits, in one re-execution (see
:func:`vision_server.decoder_limits.ensure`). Set ``MALLOC_ARENA_MAX`` yourself to choose
another value.
"""

from __future__ import annotations

PROCESS_ENV = {"MALLOC_ARENA_MAX": "2"}
"""Variables the server process should start with (unless already set)."""

__all__ = ["PROCESS_ENV"]
