"""Schema validation of every frame the conformance peer receives (SPEC §6.3.1).

:class:`FrameValidator` checks a frame's metadata against ``protocol/schema/messages/<type>.json``
and a RESULT's ``data`` against ``protocol/schema/data/<inspection type>.json``; it learns each
inspection's type from the WELCOME, INSPECTIONS and RELOADED frames it has seen. Without the
optional ``jsonschema`` package it checks nothing and says so (:attr:`FrameValidator.enabled`);
the ``metadata_schemas`` check reports that as a skip naming the package to install.
"""

from __future__ import annotations

from typing import Any

from .. import schema
from ..constants import MessageType
from ..frames import Frame

_DESCRIBING_INSPECTIONS = (MessageType.WELCOME, MessageType.INSPECTIONS, MessageType.RELOADED)


class FrameValidator:
    """Checks frames from one connection against the schemas; see :meth:`problem`."""

    def __init__(self) -> None:
        self.enabled = schema.available()
        self.inspection_types: dict[str, str] = {}
        """Inspection name → type, from the descriptors the server sent."""
        self.checked = 0
        """Frames validated so far (metadata, and the data of RESULTs whose type has a schema)."""

    def problem(self, frame: Frame) -> str | None:
        """What is wrong with ``frame`` by the schemas, or None (also when disabled, and for a
        message type protocol 1 does not define: the checks judge those themselves)."""
        if not self.enabled:
            return None
        try:
            mtype = MessageType(frame.type)
        except ValueError:
            return None
        metadata: Any = frame.metadata
        try:
            schema.validate_metadata(mtype, metadata)
            if mtype is MessageType.RESULT:
                kind = self.inspection_types.get(str(metadata.get("inspection")))
                if kind in schema.DATA_TYPES:
                    schema.validate_data(kind, metadata.get("data") or {})
        except schema.SchemaViolation as exc:
            return f"the server's {mtype.name} (request id {frame.request_id}) is invalid: {exc}"
        if mtype in _DESCRIBING_INSPECTIONS:
            self._learn(metadata.get("inspections") or [])
        self.checked += 1
        return None

    def _learn(self, descriptors: list[dict[str, Any]]) -> None:
        for item in descriptors:
            if isinstance(item.get("type"), str):
                self.inspection_types[item["name"]] = item["type"]
