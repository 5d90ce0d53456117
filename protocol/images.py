"""Images on the wire: a descriptor in the metadata, the pixels in a blob, never base64.

``ImagePayload`` is what messages carry. ``payload_from_array`` / ``array_from_payload`` convert
to and from numpy arrays (colour images BGR uint8 or gray uint8; depth uint16 millimetres).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
import numpy.typing as npt

from .constants import ImageEncoding, ImageRole
from .errors import BadImage, ImageTooLarge


@dataclass(frozen=True)
class ImagePayload:
    """One image: how it is encoded, its size in pixels, its role and its bytes.

    For PNG/JPEG, ``width`` and ``height`` may be 0 (unknown to the sender); the receiver then
    learns them when decoding.
    """

    encoding: ImageEncoding
    width: int
    height: int
    data: bytes
    role: ImageRole = ImageRole.COLOR

    def __post_init__(self) -> None:
        # Accept plain strings too ("gray8"), normalised to the enums.
        object.__setattr__(self, "encoding", ImageEncoding(self.encoding))
        object.__setattr__(self, "role", ImageRole(self.role))
        if self.width < 0 or self.height < 0:
            raise ValueError(f"image size must be non-negative, got {self.width}x{self.height}")
        if self.encoding.is_raw:
            if self.width == 0 or self.height == 0:
                raise ValueError(f"a raw {self.encoding} image needs its width and height")
            expected = self.width * self.height * self.encoding.bytes_per_pixel
            if len(self.data) != expected:
                raise ValueError(
                    f"{self.encoding} image of {self.width}x{self.height} needs {expected} bytes, "
                    f"got {len(self.data)}"
                )

    @property
    def pixels(self) -> int:
        return self.width * self.height

    def descriptor(self, blob_index: int) -> dict[str, Any]:
        return {
            "blob": blob_index,
            "encoding": self.encoding.value,
            "width": self.width,
            "height": self.height,
            "role": self.role.value,
        }


def _int_field(desc: dict[str, Any], key: str, where: str, request_id: int) -> int:
    value = desc.get(key, 0)
    if isinstance(value, bool) or not isinstance(value, int) or value < 0:
        raise BadImage(
            f"{where}.{key} must be a non-negative integer, got {value!r}", request_id=request_id
        )
    return value


def payload_from_descriptor(
    desc: Any,
    blobs: tuple[bytes, ...],
    *,
    where: str,
    request_id: int,
    max_pixels: int,
) -> ImagePayload:
    """Rebuild an ImagePayload from its metadata descriptor; typed errors name the cause."""
    if not isinstance(desc, dict):
        raise BadImage(
            f"{where} must be an object, got {type(desc).__name__}", request_id=request_id
        )
    index = _int_field(desc, "blob", where, request_id)
    if index >= len(blobs):
        raise BadImage(
            f"{where}.blob = {index} but the frame has {len(blobs)} blobs", request_id=request_id
        )
    try:
        encoding = ImageEncoding(str(desc.get("encoding")))
    except ValueError:
        raise BadImage(
            f"{where}.encoding {desc.get('encoding')!r} is not one of "
            f"{[e.value for e in ImageEncoding]}",
            request_id=request_id,
        ) from None
    try:
        role = ImageRole(desc.get("role", "color"))
    except ValueError:
        raise BadImage(
            f"{where}.role {desc.get('role')!r} is not one of {[r.value for r in ImageRole]}",
            request_id=request_id,
        ) from None
    width = _int_field(desc, "width", where, request_id)
    height = _int_field(desc, "height", where, request_id)
    if width * height > max_pixels:
        raise ImageTooLarge(
            f"{where} has {width}x{height} = {width * height} pixels, the limit is {max_pixels}",
            request_id=request_id,
            details={"pixels": width * height, "max_pixels": max_pixels},
        )
    try:
        return ImagePayload(encoding, width, height, blobs[index], role)
    except ValueError as exc:
        raise BadImage(f"{where}: {exc}", request_id=request_id) from None


def payload_from_array(
    image: npt.NDArray[Any],
    *,
    role: ImageRole = ImageRole.COLOR,
    encoding: ImageEncoding | None = None,
    jpeg_quality: int = 95,
) -> ImagePayload:
    """Wrap a numpy image: (H, W) uint8 → gray8, (H, W, 3) uint8 → bgr8, (H, W) uint16 → depth16.

    Pass ``encoding=PNG`` or ``JPEG`` to compress (JPEG only for uint8 images).
    """
    image = np.asarray(image)
    if not image.dtype.isnative:  # e.g. big-endian uint16 read from a file
        image = image.astype(image.dtype.newbyteorder("="))
    if image.ndim == 3 and image.shape[2] == 1:
        image = image[:, :, 0]
    height, width = image.shape[:2]
    if image.dtype == np.uint8 and image.ndim == 2:
        raw = ImageEncoding.GRAY8
    elif image.dtype == np.uint8 and image.ndim == 3 and image.shape[2] == 3:
        raw = ImageEncoding.BGR8
    elif image.dtype == np.uint16 and image.ndim == 2:
        raw = ImageEncoding.DEPTH16
    else:
        raise ValueError(
            f"image must be (H, W) uint8, (H, W, 3) uint8 or (H, W) uint16, "
            f"got {image.shape} {image.dtype}"
        )
    chosen = encoding or raw
    if chosen.is_raw:
        if chosen is not raw:
            raise ValueError(f"a {image.shape} {image.dtype} array cannot be sent as {chosen}")
        data = np.ascontiguousarray(image, dtype=image.dtype.newbyteorder("<")).tobytes()
        return ImagePayload(chosen, width, height, data, role)
    import cv2  # compressed encodings only

    if chosen is ImageEncoding.PNG:
        ok, buf = cv2.imencode(".png", image)
    else:
        if image.dtype != np.uint8:
            raise ValueError("JPEG takes uint8 images only; send depth as depth16 or png")
        ok, buf = cv2.imencode(".jpg", image, [cv2.IMWRITE_JPEG_QUALITY, jpeg_quality])
    if not ok:
        raise ValueError(f"OpenCV could not encode the image as {chosen}")
    return ImagePayload(chosen, width, height, buf.tobytes(), role)


_PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
_JPEG_SOI = b"\xff\xd8"
# Start-of-frame markers carry the image size; C4 (DHT), C8 (JPG) and CC (DAC) are not SOFs.
_JPEG_SOF = frozenset(range(0xC0, 0xD0)) - {0xC4, 0xC8, 0xCC}


def _jpeg_size(data: bytes) -> tuple[int, int] | None:
    position = 2
    while position + 4 <= len(data):
        if data[position] != 0xFF:
            return None
        marker = data[position + 1]
        if marker == 0xFF:  # fill byte
            position += 1
            continue
        if marker == 0x01 or 0xD0 <= marker <= 0xD8:  # markers without a length
            position += 2
            continue
        if marker in (0xD9, 0xDA):  # end of image, start of scan: no SOF before them
            return None
        length = int.from_bytes(data[position + 2 : position + 4], "big")
        if marker in _JPEG_SOF and position + 9 <= len(data):
            height = int.from_bytes(data[position + 5 : position + 7], "big")
            width = int.from_bytes(data[position + 7 : position + 9], "big")
            return width, height
        position += 2 + length
    return None


def compressed_size(payload: ImagePayload, *, request_id: int = 0) -> tuple[int, int] | None:
    """(width, height) read from a PNG/JPEG blob's header without decoding it.

    None when the header does not say (the decoder then decides). BadImage when the blob does
    not start with the signature of its encoding.
    """
    data = payload.data
    if payload.encoding is ImageEncoding.PNG:
        if not data.startswith(_PNG_SIGNATURE):
            raise BadImage(
                f"png blob of {len(data)} bytes has no PNG signature", request_id=request_id
            )
        if len(data) >= 24 and data[12:16] == b"IHDR":
            return int.from_bytes(data[16:20], "big"), int.from_bytes(data[20:24], "big")
        return None
    if payload.encoding is ImageEncoding.JPEG:
        if not data.startswith(_JPEG_SOI):
            raise BadImage(
                f"jpeg blob of {len(data)} bytes has no JPEG signature", request_id=request_id
            )
        return _jpeg_size(data)
    return payload.width, payload.height


def array_from_payload(
    payload: ImagePayload, *, request_id: int = 0, max_pixels: int | None = None
) -> npt.NDArray[Any]:
    """Decode an ImagePayload into a numpy array; BadImage names what is wrong.

    With ``max_pixels``, a PNG/JPEG whose header announces more pixels raises ImageTooLarge
    before anything is decompressed (the descriptor may say 0x0 for compressed images).
    """
    if payload.encoding is ImageEncoding.GRAY8:
        return np.frombuffer(payload.data, np.uint8).reshape(payload.height, payload.width)
    if payload.encoding is ImageEncoding.BGR8:
        return np.frombuffer(payload.data, np.uint8).reshape(payload.height, payload.width, 3)
    if payload.encoding is ImageEncoding.DEPTH16:
        return (
            np.frombuffer(payload.data, np.dtype("<u2"))
            .reshape(payload.height, payload.width)
            .astype(np.uint16)
        )
    import cv2

    size = compressed_size(payload, request_id=request_id)
    if size is not None:
        _check_size(payload, size, request_id)
        if max_pixels is not None and size[0] * size[1] > max_pixels:
            raise ImageTooLarge(
                f"{payload.encoding} image of {size[0]}x{size[1]} = {size[0] * size[1]} pixels "
                f"exceeds the limit of {max_pixels}",
                request_id=request_id,
                details={"pixels": size[0] * size[1], "max_pixels": max_pixels},
            )
    buf = np.frombuffer(payload.data, np.uint8)
    try:
        decoded = cv2.imdecode(buf, cv2.IMREAD_UNCHANGED) if buf.size else None
    except cv2.error:
        decoded = None
    if decoded is None:
        raise BadImage(
            f"{payload.encoding} blob of {len(payload.data)} bytes cannot be decoded",
            request_id=request_id,
        )
    if decoded.ndim == 3 and decoded.shape[2] == 4:
        decoded = cv2.cvtColor(decoded, cv2.COLOR_BGRA2BGR)
    h, w = decoded.shape[:2]
    _check_size(payload, (w, h), request_id)
    if decoded.dtype not in (np.uint8, np.uint16):
        raise BadImage(
            f"{payload.encoding} image has unsupported depth {decoded.dtype}", request_id=request_id
        )
    return np.asarray(decoded)


def _check_size(payload: ImagePayload, size: tuple[int, int], request_id: int) -> None:
    w, h = size
    if (payload.width and payload.width != w) or (payload.height and payload.height != h):
        raise BadImage(
            f"{payload.encoding} image is {w}x{h}, the descriptor says "
            f"{payload.width}x{payload.height}",
            request_id=request_id,
        )
