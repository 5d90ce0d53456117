"""Images uploaded to the console's try panel, as `vision-server run` reads files.

Every file passes the image gate first (:mod:`.image_gate`): its format, pixel count and
sample size are read from its header and checked against ``max_pixels`` before anything is
decoded; a format whose size cannot be read so (HDR, JPEG 2000, AVIF, a tiled or
floating-point TIFF, ...) is refused. PNG and JPEG then go to the service as they are (their
headers are checked by :func:`decode_payloads`); the other formats are decoded into the raw
payload the service takes (:func:`protocol.image_files.payload_from_file`), with OpenCV's own
limit (:mod:`vision_server.process.decoder_limits`) as the second fence. Everything runs in
the service's worker (decoding is CPU work), once the inspection is known.
"""

from __future__ import annotations

from collections.abc import Callable

from protocol import BadImage, ImageRole
from protocol.image_files import ImageFileError, payload_from_file

from ..service import ImageNeeds, Images
from .image_gate import check_upload
from .images import decode_payloads

__all__ = ["upload_loader"]

UPLOAD_NAME = "the uploaded file"


def upload_loader(data: bytes) -> Callable[[ImageNeeds], Images]:
    """A loader for an uploaded image file; BAD_IMAGE or IMAGE_TOO_LARGE naming the cause."""
    if not data:
        raise BadImage(f"{UPLOAD_NAME} is empty")

    def load(needs: ImageNeeds) -> Images:
        check_upload(data, name=UPLOAD_NAME, max_pixels=needs.max_pixels)
        try:
            payload = payload_from_file(data, name=UPLOAD_NAME, role=ImageRole.COLOR)
        except ImageFileError as exc:
            raise BadImage(str(exc)) from None
        return decode_payloads([payload], needs)

    return load
