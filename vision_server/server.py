"""The names the server had before the inspection service (kept so that code and docs that use
them keep working): :class:`VisionServer` is :class:`vision_server.app.App` (the service and the
TCP front-end), :class:`ServerSettings` the configuration's ``server:`` section.

The parts live in :mod:`vision_server.service` (the runtime), :mod:`vision_server.frontends.tcp`
(the protocol over TCP), :mod:`vision_server.app` (the wiring) and
:mod:`vision_server.config.settings`.
"""

from __future__ import annotations

from .app import App
from .config import SERVER_VERSION, ServerSettings
from .frontends import DEFAULT_MAX_FRAME_BYTES, REFUSE_HELLO_TIMEOUT_S
from .service import InspectionRecord

__version__ = SERVER_VERSION
VisionServer = App
"""The app under its older name: ``VisionServer(catalog, settings, results=, reloader=)``."""

__all__ = [
    "DEFAULT_MAX_FRAME_BYTES",
    "REFUSE_HELLO_TIMEOUT_S",
    "InspectionRecord",
    "ServerSettings",
    "VisionServer",
]
