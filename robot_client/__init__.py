"""cellvision robot client: the protocol client and, on top of it, the robot's vision skills.

Public API:

- :class:`VisionClient` (asyncio: ``connect``, ``ping``, ``list_inspections``, ``inspect``,
  ``capture``, ``close``), :class:`SyncVisionClient` (the same, blocking),
  :class:`ReconnectPolicy`, :func:`overlay_image`, :func:`wait_for_server`.
- Local errors: :class:`ClientError`, :class:`ConnectionLost`, :class:`RequestTimeout`,
  :class:`ClientClosed`. Errors the server sends are :class:`protocol.CellvisionError`
  subclasses (``protocol.UnknownInspection``, ``protocol.Busy``, ...).
- :func:`resolve_server`, :func:`parse_address`: where the server is.

The command line is ``robot-client`` (:mod:`robot_client.cli`).
"""

from .address import parse_address, resolve_server
from .client import ReconnectPolicy, SyncVisionClient, VisionClient, overlay_image, wait_for_server
from .errors import ClientClosed, ClientError, ConnectionLost, RequestTimeout

__all__ = [
    "ClientClosed",
    "ClientError",
    "ConnectionLost",
    "ReconnectPolicy",
    "RequestTimeout",
    "SyncVisionClient",
    "VisionClient",
    "overlay_image",
    "parse_address",
    "resolve_server",
    "wait_for_server",
]
