"""Counting the copies of an image on its way through the protocol (issue 16, part 3), with
buffer tracking, not timing.

One INSPECT of a ``width`` x ``height`` gray image goes from a :class:`VisionClient` to an
in-process server over loopback, and its RESULT (with a PNG overlay) comes back. What is
recorded: the buffers each side hands its transport (``WireStream.on_write``), the bytes the
transports copied into their own buffers, the body bytes each :class:`protocol.Connection`
copied on their way into a frame body (``copied_bytes``), and whether the array the inspection
reads, and the overlay the client gets, are views of the frame bodies.

For the bench: ``sys.path.insert(0, "tests/helpers")`` then ``from copies import
count_copies``; ``count_copies(1024, 768)`` returns a :class:`CopyCount` whose
``client_copies`` and ``server_copies`` are the figures (full-image copies per request).
"""

from __future__ import annotations

import asyncio
import threading
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from protocol import ImageRole, Result
from robot_client import VisionClient
from robot_client.client import overlay_image
from vision_server import Catalog, InspectionInput, InspectionOutcome
from vision_server.cameras import RequestCamera, RequestCameraSettings
from vision_server.server import ServerSettings, VisionServer
from vision_server.service import InspectionRecord


@dataclass(eq=False)
class Recorder:
    """An inspection that keeps the colour array it was given and draws a noisy overlay (so
    that its PNG is large enough to be read like an image)."""

    name: str = "recorder"
    camera: str = "tool"
    type: str = "test_recorder"
    uses_depth: bool = False
    frames: int = 1
    seen: list[np.ndarray] = field(default_factory=list)
    _lock: threading.Lock = field(default_factory=threading.Lock)

    def run(self, image: InspectionInput, *, overlay: bool) -> InspectionOutcome:
        with self._lock:
            self.seen.append(image.color)
        drawing = None
        if overlay:
            noise = np.random.default_rng(7).integers(0, 256, image.color.shape[:2], np.uint8)
            drawing = np.dstack([noise, image.color, noise])
        return InspectionOutcome(True, {"shape": list(image.color.shape)}, drawing)


def recorder_catalog(recorder: Recorder) -> Catalog:
    return Catalog.build([RequestCamera("tool", RequestCameraSettings())], [recorder])


def exporter(array: Any) -> object:
    """The object that owns ``array``'s memory: the end of its chain of views."""
    owner: Any = array
    while True:
        if isinstance(owner, memoryview):
            owner = owner.obj
        elif isinstance(owner, np.ndarray) and owner.base is not None:
            owner = owner.base
        else:
            return owner


def is_frame_body(owner: object) -> bool:
    """Whether ``owner`` is a frame body as a connection makes one (protocol.frames.new_body):
    a bytearray, or for a large body a flat uint8 array of its own memory."""
    if isinstance(owner, bytearray):
        return True
    return (
        isinstance(owner, np.ndarray)
        and owner.base is None
        and owner.ndim == 1
        and owner.dtype == np.uint8
    )


@dataclass
class CopyCount:
    """The copies of one INSPECT and its RESULT (bytes; "copied" never counts the socket's
    own read or write, i.e. the kernel's copy)."""

    image_bytes: int
    client_views_share_array: bool
    """The client handed its transport a buffer that is a view of the caller's array."""
    client_joined: bool
    """Some buffer handed to the client's transport holds the image joined with other bytes."""
    client_transport_copied: int
    """Image bytes asyncio's socket transport copied into its buffer (the kernel did not take
    them at once; Python 3.11's selector transport copies the unsent tail)."""
    server_body_copied: int
    """Request body bytes the server's connection copied on their way into the frame body."""
    server_array_shares_body: bool
    """The array the inspection read is a view of the received frame body."""
    overlay_bytes: int
    server_overlay_view: bool
    """The server handed its transport the overlay PNG as it was encoded (a view, no join)."""
    server_transport_copied: int
    client_body_copied: int
    """RESULT body bytes the client's connection copied on their way into the frame body."""
    client_overlay_in_body: bool
    """The overlay the client got is a view of the received frame body."""

    @property
    def server_copies(self) -> float:
        """Full copies of the image on the server between socket and inspection (0..1)."""
        return self.server_body_copied / self.image_bytes

    @property
    def client_copies(self) -> float:
        """Full copies of the image on the client beyond the socket write (0..1)."""
        return self.client_transport_copied / self.image_bytes

    def as_dict(self) -> dict[str, Any]:
        return {
            **{k: v for k, v in vars(self).items()},
            "server_copies": self.server_copies,
            "client_copies": self.client_copies,
        }


async def measure_copies(width: int = 1024, height: int = 768, *, rounds: int = 1) -> CopyCount:
    """One connection, ``rounds`` INSPECTs (the last is counted) of a ``width`` x ``height``
    uint8 gray image with an overlay; see :class:`CopyCount`."""
    recorder = Recorder()
    replies: list[InspectionRecord] = []
    image = np.random.default_rng(1).integers(0, 256, (height, width), np.uint8)
    server = VisionServer(recorder_catalog(recorder), ServerSettings(port=0, workers=1))
    await server.start()
    try:
        server.service.subscribe(replies.append)
        async with VisionClient("127.0.0.1", server.port, request_timeout_s=30.0) as client:
            (session,) = server.tcp.connections
            client_stream, server_stream = client.stream, session.stream
            assert client_stream is not None
            result: Result | None = None
            for _ in range(rounds):
                client_sent: list[memoryview] = []
                server_sent: list[memoryview] = []
                client_stream.on_write = client_sent.append
                server_stream.on_write = server_sent.append
                before = (
                    client_stream.write_copied_bytes,
                    session.conn.copied_bytes,
                    server_stream.write_copied_bytes,
                    client_stream.conn.copied_bytes if client_stream.conn else 0,
                )
                result = await client.inspect(recorder.name, image, overlay=True)
            assert result is not None
            assert client_stream.conn is not None
            overlay = next(p for p in result.images if p.role is ImageRole.OVERLAY)
            encoded = replies[-1].reply.overlay
            assert encoded is not None
            assert encoded.encoded is not None
            decoded = overlay_image(result)
            assert decoded is not None
            assert decoded.shape[:2] == (height, width)
            seen = recorder.seen[-1]
            body = exporter(seen)
            return CopyCount(
                image_bytes=image.nbytes,
                client_views_share_array=any(
                    len(v) == image.nbytes and np.shares_memory(np.asarray(v), image)
                    for v in client_sent
                ),
                client_joined=any(len(v) > image.nbytes for v in client_sent),
                client_transport_copied=client_stream.write_copied_bytes - before[0],
                server_body_copied=session.conn.copied_bytes - before[1],
                server_array_shares_body=is_frame_body(body)
                and image.nbytes < len(body) < image.nbytes + 4096
                and np.shares_memory(seen, np.frombuffer(body, np.uint8))
                and np.array_equal(seen, image),
                overlay_bytes=len(overlay.data),
                server_overlay_view=any(
                    len(v) == len(encoded.encoded) and exporter(v) is encoded.encoded
                    for v in server_sent
                ),
                server_transport_copied=server_stream.write_copied_bytes - before[2],
                client_body_copied=client_stream.conn.copied_bytes - before[3],
                client_overlay_in_body=is_frame_body(exporter(overlay.data))
                and bytes(overlay.data) == encoded.encoded,
            )
    finally:
        await server.stop()


def count_copies(width: int = 1024, height: int = 768, *, rounds: int = 1) -> CopyCount:
    """:func:`measure_copies` on a fresh event loop (for the bench and for scripts)."""
    return asyncio.run(measure_copies(width, height, rounds=rounds))
