"""cellvision vision server: named inspections served over the cellvision protocol.

Public API:

- :class:`VisionServer` (``start``, ``serve_forever``, ``stop``, ``replace_catalog``, ``port``),
  :class:`ServerSettings`.
- :class:`Catalog`, :class:`Inspection` (the protocol an inspection
  implements), :class:`InspectionInput`, :class:`InspectionOutcome`.
- :func:`builtin_catalog`: what ``vision-server serve`` offers without a configuration file.

The command line is ``vision-server`` (:mod:`vision_server.cli`).
"""

from .builtin import builtin_catalog
from .catalog import Catalog, Inspection, InspectionInput, InspectionOutcome
from .server import ServerSettings, VisionServer

__all__ = [
    "Catalog",
    "Inspection",
    "InspectionInput",
    "InspectionOutcome",
    "ServerSettings",
    "VisionServer",
    "builtin_catalog",
]
