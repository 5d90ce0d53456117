"""The ``metadata_schemas`` check (SPEC §6.3.1): one session that makes the server send every
kind of answer it can (INSPECTIONS, PONG, a RESULT or ERROR per inspection it offers, FRAMES
or ERROR per server camera), all checked against ``protocol/schema`` by the peer's validator.

The peer validates every frame of every check; this check adds the answers the other checks
never ask for (a RESULT of each inspection type, FRAMES with intrinsics), and is where a run
without ``jsonschema`` says that nothing was validated.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from .. import schema
from ..constants import ImageRole, MessageType
from ..frames import Frame
from ..images import ImagePayload, payload_from_array
from ..messages import Capture, Inspect, ListInspections, Ping
from .checks import Context, Skip, check
from .peer import CLOSED, CheckFailed, Peer

MAX_INSPECTIONS = 16
"""Inspections (and cameras) asked at most, so that a large catalog keeps the check short."""


def _answer(peer: Peer, request_id: int, wanted: MessageType) -> Frame:
    """The answer to ``request_id``: ``wanted`` or ERROR (frames of other ids are skipped)."""
    while True:
        frame = peer.recv_frame()
        if frame is CLOSED:
            raise CheckFailed(f"the server closed the connection before its {wanted.name}")
        assert isinstance(frame, Frame)
        if frame.request_id == request_id and frame.type in (wanted, MessageType.ERROR):
            return frame


def _images(descriptor: dict[str, Any]) -> tuple[ImagePayload, ...]:
    """A small gray gradient, and a flat depth image of 0.5 m when the inspection needs depth."""
    gray = np.tile(np.linspace(0, 255, 64, dtype=np.uint8), (48, 1))
    images = [payload_from_array(gray)]
    if descriptor.get("depth") is True:
        depth = np.full((48, 64), 500, dtype=np.uint16)
        images.append(payload_from_array(depth, role=ImageRole.DEPTH))
    return tuple(images)


@check(
    "metadata_schemas",
    "§6.3.1",
    "every answer (a RESULT of each inspection, FRAMES of each camera) matches protocol/schema",
)
def _metadata_schemas(ctx: Context) -> None:
    if not schema.available():
        raise Skip(
            "jsonschema is not installed, so no message of this run was validated against "
            f"protocol/schema: {schema.INSTALL_HINT}"
        )
    with ctx.open() as peer:
        peer.send(ListInspections(2))
        _answer(peer, 2, MessageType.INSPECTIONS)
        peer.send(Ping(3, "schemas"))
        _answer(peer, 3, MessageType.PONG)
        request_id = 10
        for item in ctx.inspections[:MAX_INSPECTIONS]:
            request = item.get("camera_source") == "request"
            images = _images(item) if request else ()
            peer.send(Inspect(request_id, str(item["name"]), images))
            _answer(peer, request_id, MessageType.RESULT)
            request_id += 1
        for camera in ctx.cameras[:MAX_INSPECTIONS]:
            if camera.get("source") in ("request", None):
                continue
            peer.send(Capture(request_id, str(camera["name"]), 1, bool(camera.get("depth"))))
            _answer(peer, request_id, MessageType.FRAMES)
            request_id += 1
        if peer.validator.checked == 0:
            raise CheckFailed("the validator checked no frame")
