"""Wire constants of protocol v1: the frame header, message types, image encodings, defaults.

Every multi-byte integer on the wire is little-endian.
"""

from __future__ import annotations

import struct
from enum import IntEnum, StrEnum
from typing import Final

MAGIC: Final = b"CVIS"
"""The four bytes every frame starts with (0x43 0x56 0x49 0x53)."""

HEADER: Final = struct.Struct("<4sBBHHHIII")
"""magic, major, minor, type, flags, blob count, request id, metadata length, body length."""

HEADER_SIZE: Final = HEADER.size  # 24 bytes
BLOB_LENGTH: Final = struct.Struct("<I")

PROTOCOL_VERSION: Final = (1, 1)
"""The newest (major, minor) this implementation speaks."""

SUPPORTED_VERSIONS: Final = ((1, 1),)

DEFAULT_PORT: Final = 7878
"""The documented default TCP port of a cellvision server."""

MAX_U32: Final = 0xFFFFFFFF
NO_REQUEST: Final = 0
"""The request id of connection-level messages (CLOSE, an ERROR not tied to a request)."""


class MessageType(IntEnum):
    """The message type field of the header (u16)."""

    HELLO = 0x0001
    WELCOME = 0x0002
    PING = 0x0003
    PONG = 0x0004
    CLOSE = 0x0005
    LIST_INSPECTIONS = 0x0010
    INSPECTIONS = 0x0011
    INSPECT = 0x0020
    RESULT = 0x0021
    CAPTURE = 0x0030
    FRAMES = 0x0031
    RELOAD = 0x0040
    RELOADED = 0x0041
    OPERATOR_CALL = 0x0050
    OPERATOR_ANSWER = 0x0051
    ERROR = 0x00FF


class ImageEncoding(StrEnum):
    """How an image blob is encoded. Raw encodings are row-major, no padding."""

    GRAY8 = "gray8"
    """uint8, one channel: width * height bytes."""
    BGR8 = "bgr8"
    """uint8, three channels in B, G, R order: width * height * 3 bytes."""
    DEPTH16 = "depth16"
    """uint16 little-endian millimetres, 0 = no depth: width * height * 2 bytes."""
    PNG = "png"
    JPEG = "jpeg"

    @property
    def is_raw(self) -> bool:
        return self in (ImageEncoding.GRAY8, ImageEncoding.BGR8, ImageEncoding.DEPTH16)

    @property
    def bytes_per_pixel(self) -> int:
        """Bytes per pixel of a raw encoding; 0 for compressed ones."""
        return {"gray8": 1, "bgr8": 3, "depth16": 2}.get(self.value, 0)


class ImageRole(StrEnum):
    """What an image in a request or response is."""

    COLOR = "color"
    DEPTH = "depth"
    OVERLAY = "overlay"
