"""How glibc's malloc should behave in the server process: fewer arenas, and request bodies
that reuse freed memory instead of fresh pages.

- ``MALLOC_ARENA_MAX=2``. glibc gives each thread that allocates under contention an arena of
  its own (up to 8 per core) and rarely returns an arena's freed memory to the system. The
  server's threads (the event loop, the workers of both lanes, the result log's writer) each
  allocate and free request bodies of up to ``max_frame_bytes``. Measured with the
  hostile-frame soak (scripts/soak.py, 1,000 frames), the server's peak RSS ranged from 204 to
  497 MiB over 9 runs with glibc's default, and from 237 to 327 MiB over 3 runs started with
  two arenas (the soak's bound: 416 MiB).
- ``MALLOC_MMAP_THRESHOLD_`` and ``MALLOC_TRIM_THRESHOLD_`` at 32 MiB and 64 MiB. By default a
  request body (786 KB for a 1024x768 colour image) is above glibc's mmap threshold: each one
  was a fresh mapping, zeroed by the kernel page by page as the socket's bytes were copied in,
  and unmapped when the request ended. Measured with 16 clients sending brightness requests
  one at a time (a cell of bench section 2): 133 minor page faults per request and 1.5 ms of
  server CPU per answer; with the thresholds, 2.8 faults and 0.9 ms. Bodies up to 32 MiB
  (the largest glibc allows for the threshold) now come from the heap and reuse what earlier
  requests freed; up to 64 MiB of freed memory stays at the top of a heap rather than being
  returned and faulted in again (a bounded cost: the budget ``max_buffered_bytes`` bounds what
  is in use).

glibc reads these when the process starts (``mallopt`` later, once threads have allocated, was
measured to change nothing for the arenas), so ``vision-server serve`` starts itself again with
them when they are not set, with OpenCV's limits, in one re-execution (see
:func:`vision_server.process.decoder_limits.ensure`). Set any of them yourself to choose
another value.
The worker processes of ``process_inspections`` inherit them.
"""

from __future__ import annotations

MMAP_THRESHOLD_BYTES = 32 * 1024 * 1024
"""glibc's largest mmap threshold on 64-bit systems; a larger value would be ignored."""
TRIM_THRESHOLD_BYTES = 64 * 1024 * 1024

PROCESS_ENV = {
    "MALLOC_ARENA_MAX": "2",
    "MALLOC_MMAP_THRESHOLD_": str(MMAP_THRESHOLD_BYTES),
    "MALLOC_TRIM_THRESHOLD_": str(TRIM_THRESHOLD_BYTES),
}
"""Variables the server process should start with (unless already set)."""

__all__ = ["PROCESS_ENV"]
