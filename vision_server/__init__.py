"""cellvision vision server: named inspections served over the cellvision protocol.

Public API:

- :class:`InspectionService` (``inspect``, ``capture``, ``admit``, ``reload``, ``subscribe``),
  the one path to an inspection, with its records :class:`InspectRequest`, :class:`Images`,
  :class:`InspectReply`.
- :class:`VisionServer` (the service with the TCP front-end: ``start``, ``serve_forever``,
  ``stop``, ``replace_catalog``, ``port``, ``service``, ``tcp``), :class:`ServerSettings`.
- :class:`Catalog`, :class:`Inspection` (the protocol an inspection
  implements), :class:`InspectionInput`, :class:`InspectionOutcome`.
- :func:`builtin_catalog`: what ``vision-server serve`` offers without a configuration file.

The command line is ``vision-server`` (:mod:`vision_server.commands.program`).
"""

# First, before anything imports cv2: OpenCV reads its image-size limits when it loads.
from .process import decoder_limits

decoder_limits.install_default()

# The imports below load cv2, so they come after the limits (hence E402).
from .inspections import Inspection, InspectionInput, InspectionOutcome  # noqa: E402
from .server import ServerSettings, VisionServer  # noqa: E402
from .service import (  # noqa: E402
    Catalog,  # noqa: E402
    Images,
    InspectionService,
    InspectReply,
    InspectRequest,
    builtin_catalog,  # noqa: E402
)

__all__ = [
    "Catalog",
    "Images",
    "Inspection",
    "InspectionInput",
    "InspectionOutcome",
    "InspectionService",
    "InspectReply",
    "InspectRequest",
    "ServerSettings",
    "VisionServer",
    "builtin_catalog",
]
