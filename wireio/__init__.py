"""asyncio I/O for the sans-IO :mod:`protocol`: a ``BufferedProtocol`` stream that receives
straight into a :class:`protocol.Connection`'s frame bodies and sends its frames as lists of
buffers (no intermediate ``bytes``, no join).

Public API:

- :class:`WireStream`: one connection; ``receive()`` (pulled by the owner: a body is read
  into its buffer once the connection has admitted its header; ``interrupt()`` ends a wait
  with :data:`INTERRUPTED`), ``pause_reading()`` / ``resume_reading()``,
  ``writelines(parts)`` / ``write`` (one ``writev`` per message), ``drain()`` (needed only
  while ``write_paused``), ``close()``, ``abort()``, ``wait_closed()``, ``get_extra_info()``,
  ``start_tls()``.
- :func:`serve` (a listening server for ``loop.create_server``) and :func:`open_connection`.
- :class:`FrameCursor`: where a byte stream is, frame by frame.

Imports only :mod:`protocol` and asyncio; ``vision_server`` and ``robot_client`` use it.
"""

from .endpoints import open_connection, serve
from .framing import FrameCursor
from .stream import INTERRUPTED, READ_BUFFER_BYTES, WireStream

__all__ = [
    "INTERRUPTED",
    "READ_BUFFER_BYTES",
    "FrameCursor",
    "WireStream",
    "open_connection",
    "serve",
]
