"""Image payloads (the protocol's image encodings, SPEC §4) decoded into the service's arrays.

Used by the TCP front-end for the images of an INSPECT and by the offline tools for image files
(which :func:`protocol.image_files.payload_from_file` reads into the same payloads). The loader
runs once the inspection is known: in a worker thread of the service (decoding is CPU work), or
on the event loop when it is ``cheap`` (raw pixels, viewed in place) and the inspection too.

Wire-level checks are made here, before anything is decompressed: the number of colour images,
and each compressed header's bit depth and channels (a 16-bit colour PNG is refused without
decoding it). The array-level checks (dtype, registration, pixel limit) are the service's,
whoever decoded the images.
"""

from __future__ import annotations

from collections.abc import Sequence

from protocol import BadImage, ImagePayload, ImageRole, array_from_payload
from protocol.images import compressed_header

from ..service import ImageLoader, ImageNeeds, Images, check_image_size


class PayloadLoader:
    """The images of one request, decoded when the service calls it; ``cheap`` when every
    one is raw pixels (viewed in place: the service may load them on the event loop)."""

    def __init__(self, payloads: Sequence[ImagePayload]) -> None:
        self._payloads = tuple(payloads)
        self.cheap = all(p.encoding.is_raw for p in self._payloads)
        self.raw_bytes = sum(len(p.data) for p in self._payloads) if self.cheap else 0
        """The bytes of the pixels when they are all raw (checked when they are viewed)."""

    def __call__(self, needs: ImageNeeds) -> Images:
        return decode_payloads(self._payloads, needs)


def payload_loader(payloads: Sequence[ImagePayload]) -> ImageLoader:
    """A loader for the images of one request (:class:`PayloadLoader`)."""
    return PayloadLoader(payloads)


def decode_payloads(payloads: Sequence[ImagePayload], needs: ImageNeeds) -> Images:
    """One colour image and the depth frames of a request, as arrays; BAD_IMAGE or
    IMAGE_TOO_LARGE naming the cause."""
    colors = [p for p in payloads if p.role is ImageRole.COLOR]
    depths = [p for p in payloads if p.role is ImageRole.DEPTH]
    if len(colors) != 1:
        raise BadImage(
            f"inspection {needs.inspection!r} takes exactly one colour image, the request has "
            f"{len(colors)}"
        )
    if depths and not needs.depth:
        raise BadImage(
            f"inspection {needs.inspection!r} takes no depth image, the request has {len(depths)}"
        )
    # Every header is read before anything is decoded: a 16-bit colour PNG, or a colour depth
    # image, is refused without decompressing it (the decoded array is checked again).
    for payload in (colors[0], *depths):
        if payload.encoding.is_raw:
            continue
        header = compressed_header(payload, max_pixels=needs.max_pixels)
        if payload.role is ImageRole.COLOR:
            # Before decoding: an image of another size than the intrinsics is refused anyway.
            check_image_size(header.width, header.height, needs)
        if payload.role is ImageRole.COLOR and header.bits != 8:
            raise BadImage(
                f"the colour image is a {header.bits}-bit {payload.encoding}; it must be 8-bit"
            )
        if payload.role is ImageRole.DEPTH and (header.bits, header.channels) != (16, 1):
            raise BadImage(
                f"a depth image must be 16-bit gray (millimetres); this {payload.encoding} has "
                f"{header.channels} channel(s) of {header.bits} bits"
            )
    color = array_from_payload(colors[0], max_pixels=needs.max_pixels)
    depth = tuple(array_from_payload(p, max_pixels=needs.max_pixels) for p in depths)
    return Images(color, depth)


__all__ = ["PayloadLoader", "decode_payloads", "payload_loader"]
