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
from .frames import MAX_SAFE_INTEGER, Blob, as_integer, blob_view
from .image_headers import ImageHeader, jpeg_header, png_header


@dataclass(frozen=True)
class ImagePayload:
    """One image: how it is encoded, its size in pixels, its role and its bytes.

    For PNG/JPEG, ``width`` and ``height`` may be 0 (unknown to the sender); the receiver then
    learns them when decoding.

    ``data`` is any bytes-like buffer; it is kept as a flat read-only view, not copied. A
    received payload views its frame's body; one made by :func:`payload_from_array` views the
    caller's array, which must then not change until the message is sent.
    """

    encoding: ImageEncoding
    width: int
    height: int
    data: Blob
    role: ImageRole = ImageRole.COLOR

    def __post_init__(self) -> None:
        if not isinstance(self.data, bytes):
            object.__setattr__(self, "data", blob_view(self.data))
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
    value = desc.get(key)
    if value is None:  # absent or null (SPEC §3.2): 0, "unknown" (a raw image then fails)
        return 0
    number = as_integer(value)
    if number is None or number < 0:
        raise BadImage(
            f"{where}.{key} must be a non-negative integer, got {value!r}", request_id=request_id
        )
    return number


def too_large_details(width: int, height: int, max_pixels: int) -> dict[str, int]:
    """The ``details`` of IMAGE_TOO_LARGE (SPEC §4.3): the image's ``width`` and ``height`` in
    pixels and ``pixels`` = width x height, clamped to 2**53 - 1 so that it stays I-JSON (two
    u32 sides multiply to far more; their exact product is width x height)."""
    return {
        "pixels": min(width * height, MAX_SAFE_INTEGER),
        "width": min(width, MAX_SAFE_INTEGER),
        "height": min(height, MAX_SAFE_INTEGER),
        "max_pixels": max_pixels,
    }


def payload_from_descriptor(
    desc: Any,
    blobs: tuple[Blob, ...],
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
    role_value = desc.get("role")
    try:
        role = ImageRole("color" if role_value is None else role_value)  # null = absent
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
            details=too_large_details(width, height, max_pixels),
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
        # A view of the caller's pixels (a copy only when they are not contiguous little-endian
        # already): the frame writes them to the socket from there.
        pixels = np.ascontiguousarray(image, dtype=image.dtype.newbyteorder("<"))
        return ImagePayload(chosen, width, height, blob_view(pixels.data), role)
    import cv2  # compressed encodings only

    if chosen is ImageEncoding.PNG:
        ok, buf = cv2.imencode(".png", image)
    else:
        if image.dtype != np.uint8:
            raise ValueError("JPEG takes uint8 images only; send depth as depth16 or png")
        ok, buf = cv2.imencode(".jpg", image, [cv2.IMWRITE_JPEG_QUALITY, jpeg_quality])
    if not ok:
        raise ValueError(f"OpenCV could not encode the image as {chosen}")
    return ImagePayload(chosen, width, height, blob_view(buf.data), role)


def compressed_header(
    payload: ImagePayload, *, request_id: int = 0, max_pixels: int | None = None
) -> ImageHeader:
    """What decoding a PNG/JPEG blob will produce, read from its header without decoding it.

    BadImage (naming the cause) when the header does not establish the size the decoder would
    use: there is no "unknown" answer, so nothing is ever decoded unchecked (SPEC §4.3).
    ImageTooLarge when it has more than ``max_pixels`` pixels.
    """
    # The header readers search with bytes methods; a compressed blob is small next to the
    # pixels it decodes into, and is copied only here.
    data = payload.data if isinstance(payload.data, bytes) else bytes(payload.data)
    if payload.encoding is ImageEncoding.PNG:
        header = png_header(data, request_id=request_id)
    elif payload.encoding is ImageEncoding.JPEG:
        header = jpeg_header(data, request_id=request_id)
    else:
        raise ValueError(f"{payload.encoding} is not a compressed encoding")
    if max_pixels is not None and header.pixels > max_pixels:
        raise ImageTooLarge(
            f"{payload.encoding} image of {header.width}x{header.height} = {header.pixels} "
            f"pixels exceeds the limit of {max_pixels}",
            request_id=request_id,
            details=too_large_details(header.width, header.height, max_pixels),
        )
    return header


def compressed_size(payload: ImagePayload, *, request_id: int = 0) -> tuple[int, int]:
    """(width, height) of a PNG/JPEG blob from its header; see :func:`compressed_header`."""
    header = compressed_header(payload, request_id=request_id)
    return header.width, header.height


def array_from_payload(
    payload: ImagePayload, *, request_id: int = 0, max_pixels: int | None = None
) -> npt.NDArray[Any]:
    """Decode an ImagePayload into a numpy array; BadImage names what is wrong.

    PNG/JPEG: the size is read from the file's header first (:func:`compressed_header`); with
    ``max_pixels``, more pixels raise ImageTooLarge before anything is decompressed (the
    descriptor may say 0x0 for compressed images). The result is (H, W) for gray files and
    (H, W, 3) BGR for colour ones, uint8 or (16-bit PNG) uint16; alpha is dropped.
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
    header = compressed_header(payload, request_id=request_id, max_pixels=max_pixels)
    _check_size(payload, (header.width, header.height), request_id)
    decoded = _decode(payload, header, request_id)
    expected: tuple[int, ...] = (header.height, header.width)
    if header.channels > 1:
        expected += (header.channels,)
    if decoded.shape != expected or decoded.dtype.itemsize * 8 != header.bits:
        # The decoder read the file otherwise than its header says: never hand that on.
        raise BadImage(
            f"{payload.encoding} decoder produced {decoded.shape} {decoded.dtype}, the header "
            f"says {header.width}x{header.height}, {header.channels} channel(s) of "
            f"{header.bits} bits",
            request_id=request_id,
        )
    return decoded


def _decode(payload: ImagePayload, header: ImageHeader, request_id: int) -> npt.NDArray[Any]:
    import cv2

    # The mode follows the header, so the decoder allocates only the array we return: gray
    # stays one channel, alpha is stripped while decoding (no BGRA copy), 16 bits stay 16.
    # EXIF orientation is ignored, as the size check assumed the stored orientation.
    mode = cv2.IMREAD_GRAYSCALE if header.channels == 1 else cv2.IMREAD_COLOR
    flags = mode | cv2.IMREAD_ANYDEPTH | cv2.IMREAD_IGNORE_ORIENTATION
    try:
        decoded = cv2.imdecode(np.frombuffer(payload.data, np.uint8), flags)
    except cv2.error as exc:
        # OpenCV's own size limits (vision_server.process.decoder_limits) end up here, as do its
        # decoders' hard errors.
        raise BadImage(
            f"{payload.encoding} blob of {len(payload.data)} bytes cannot be decoded: "
            f"{_first_line(str(exc))}",
            request_id=request_id,
        ) from None
    if decoded is None:
        raise BadImage(
            f"{payload.encoding} blob of {len(payload.data)} bytes cannot be decoded",
            request_id=request_id,
        )
    return np.asarray(decoded)


def _first_line(text: str) -> str:
    lines = [line.strip() for line in text.strip().splitlines() if line.strip()]
    return lines[-1] if lines else "decoder error"


def _check_size(payload: ImagePayload, size: tuple[int, int], request_id: int) -> None:
    w, h = size
    if (payload.width and payload.width != w) or (payload.height and payload.height != h):
        raise BadImage(
            f"{payload.encoding} image is {w}x{h}, the descriptor says "
            f"{payload.width}x{payload.height}",
            request_id=request_id,
        )
