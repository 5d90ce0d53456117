"""Error taxonomy: every wire error code, and one exception class per code.

An exception class carries its wire code (``code``) and whether the connection survives it
(``fatal``). The same classes are raised by the sans-IO connection when the peer's bytes are bad,
raised by servers to answer a request with an ERROR, and rebuilt on the client from an ERROR
message with :func:`error_from_code`.

:class:`LocalProtocolError` is different: it means *our own* code tried to break the protocol
(send a message the state machine does not allow); it has no wire code.
"""

from __future__ import annotations

from dataclasses import dataclass
from enum import IntEnum
from typing import Any, ClassVar


class ErrorCode(IntEnum):
    """Stable numeric error codes (u16 range) carried by ERROR messages."""

    MALFORMED_FRAME = 1
    UNSUPPORTED_VERSION = 2
    FRAME_TOO_LARGE = 3
    UNKNOWN_MESSAGE_TYPE = 4
    BAD_METADATA = 5
    UNEXPECTED_MESSAGE = 6
    DUPLICATE_REQUEST_ID = 7
    NOT_AUTHENTICATED = 8
    UNKNOWN_INSPECTION = 10
    UNKNOWN_CAMERA = 11
    BAD_IMAGE = 12
    IMAGE_TOO_LARGE = 13
    CAMERA_UNAVAILABLE = 14
    INSPECTION_FAILED = 15
    INVALID_ARGUMENT = 16
    CONFIG_INVALID = 17
    BUSY = 20
    DEADLINE_EXCEEDED = 21
    SHUTTING_DOWN = 22
    INTERNAL_ERROR = 30


@dataclass(frozen=True)
class ErrorInfo:
    fatal: bool
    meaning: str


ERROR_TABLE: dict[ErrorCode, ErrorInfo] = {
    ErrorCode.MALFORMED_FRAME: ErrorInfo(True, "bad magic, or lengths that do not add up"),
    ErrorCode.UNSUPPORTED_VERSION: ErrorInfo(
        True, "no common major version, or a frame of the wrong major"
    ),
    ErrorCode.FRAME_TOO_LARGE: ErrorInfo(True, "the header announces more bytes than the limit"),
    ErrorCode.UNKNOWN_MESSAGE_TYPE: ErrorInfo(False, "a message type this peer does not know"),
    ErrorCode.BAD_METADATA: ErrorInfo(
        False, "metadata is not a UTF-8 JSON object, or a field is missing or of the wrong type"
    ),
    ErrorCode.UNEXPECTED_MESSAGE: ErrorInfo(
        False, "a known message in the wrong direction or state"
    ),
    ErrorCode.DUPLICATE_REQUEST_ID: ErrorInfo(
        True, "a request id that is still in flight on this connection"
    ),
    ErrorCode.NOT_AUTHENTICATED: ErrorInfo(
        True, "a request before a successful HELLO, or a wrong token"
    ),
    ErrorCode.UNKNOWN_INSPECTION: ErrorInfo(False, "no inspection of that name"),
    ErrorCode.UNKNOWN_CAMERA: ErrorInfo(False, "no camera of that name"),
    ErrorCode.BAD_IMAGE: ErrorInfo(
        False, "an image that cannot be decoded or does not fit its description"
    ),
    ErrorCode.IMAGE_TOO_LARGE: ErrorInfo(False, "an image with more pixels than the limit"),
    ErrorCode.CAMERA_UNAVAILABLE: ErrorInfo(False, "the camera exists but gives no frame now"),
    ErrorCode.INSPECTION_FAILED: ErrorInfo(
        False, "the inspection could not be computed on this input"
    ),
    ErrorCode.INVALID_ARGUMENT: ErrorInfo(False, "a request parameter out of range"),
    ErrorCode.CONFIG_INVALID: ErrorInfo(
        False, "the re-read configuration is invalid; the server keeps the old one"
    ),
    ErrorCode.BUSY: ErrorInfo(
        False, "over capacity: try again later (`details.retry_after_ms`, §6.1)"
    ),
    ErrorCode.DEADLINE_EXCEEDED: ErrorInfo(
        False, "the request's deadline passed before it was done"
    ),
    ErrorCode.SHUTTING_DOWN: ErrorInfo(
        False, "the server is stopping: this request was not done; CLOSE follows"
    ),
    ErrorCode.INTERNAL_ERROR: ErrorInfo(
        False, "a bug in the server: the request failed, the connection survives"
    ),
}


class CellvisionError(Exception):
    """Base of every error with a wire code.

    ``request_id`` is the id of the request the error answers (0 when it concerns the
    connection). ``details`` is extra JSON-able data sent along. ``fatal`` overrides the
    table; it is set when the error was rebuilt from an ERROR whose sender said otherwise (the
    sender closes the connection after a fatal ERROR, whatever our table says).
    """

    code: ClassVar[ErrorCode] = ErrorCode.INTERNAL_ERROR

    def __init__(
        self,
        message: str,
        *,
        request_id: int = 0,
        details: dict[str, Any] | None = None,
        fatal: bool | None = None,
    ) -> None:
        super().__init__(message)
        self.message = message
        self.request_id = request_id
        self.details: dict[str, Any] = dict(details or {})
        self._fatal = fatal

    @property
    def fatal(self) -> bool:
        """True when the connection is closed after this error."""
        return ERROR_TABLE[self.code].fatal if self._fatal is None else self._fatal

    def __repr__(self) -> str:
        return f"{type(self).__name__}({self.message!r}, request_id={self.request_id})"


class MalformedFrame(CellvisionError):
    code = ErrorCode.MALFORMED_FRAME


class UnsupportedVersion(CellvisionError):
    code = ErrorCode.UNSUPPORTED_VERSION


class FrameTooLarge(CellvisionError):
    code = ErrorCode.FRAME_TOO_LARGE


class UnknownMessageType(CellvisionError):
    code = ErrorCode.UNKNOWN_MESSAGE_TYPE


class BadMetadata(CellvisionError):
    code = ErrorCode.BAD_METADATA


class UnexpectedMessage(CellvisionError):
    code = ErrorCode.UNEXPECTED_MESSAGE


class DuplicateRequestId(CellvisionError):
    code = ErrorCode.DUPLICATE_REQUEST_ID


class NotAuthenticated(CellvisionError):
    code = ErrorCode.NOT_AUTHENTICATED


class UnknownInspection(CellvisionError):
    code = ErrorCode.UNKNOWN_INSPECTION


class UnknownCamera(CellvisionError):
    code = ErrorCode.UNKNOWN_CAMERA


class BadImage(CellvisionError):
    code = ErrorCode.BAD_IMAGE


class ImageTooLarge(CellvisionError):
    code = ErrorCode.IMAGE_TOO_LARGE


class CameraUnavailable(CellvisionError):
    code = ErrorCode.CAMERA_UNAVAILABLE


class InspectionFailed(CellvisionError):
    code = ErrorCode.INSPECTION_FAILED


class InvalidArgument(CellvisionError):
    code = ErrorCode.INVALID_ARGUMENT


class ConfigInvalid(CellvisionError):
    code = ErrorCode.CONFIG_INVALID


class Busy(CellvisionError):
    code = ErrorCode.BUSY


class DeadlineExceeded(CellvisionError):
    code = ErrorCode.DEADLINE_EXCEEDED


class ShuttingDown(CellvisionError):
    code = ErrorCode.SHUTTING_DOWN


class InternalError(CellvisionError):
    code = ErrorCode.INTERNAL_ERROR


class UnknownErrorCode(CellvisionError):
    """An ERROR whose code this implementation does not know (a newer peer).

    Its ``code`` is INTERNAL_ERROR for classification; ``wire_code`` keeps the number received.
    Treated as non-fatal unless the peer said it was fatal.
    """

    def __init__(self, message: str, *, wire_code: int, peer_fatal: bool, **kwargs: Any) -> None:
        super().__init__(message, fatal=peer_fatal, **kwargs)
        self.wire_code = wire_code


ERROR_CLASSES: dict[ErrorCode, type[CellvisionError]] = {
    cls.code: cls
    for cls in (
        MalformedFrame,
        UnsupportedVersion,
        FrameTooLarge,
        UnknownMessageType,
        BadMetadata,
        UnexpectedMessage,
        DuplicateRequestId,
        NotAuthenticated,
        UnknownInspection,
        UnknownCamera,
        BadImage,
        ImageTooLarge,
        CameraUnavailable,
        InspectionFailed,
        InvalidArgument,
        ConfigInvalid,
        Busy,
        DeadlineExceeded,
        ShuttingDown,
        InternalError,
    )
}


def error_from_code(
    code: int,
    message: str,
    *,
    request_id: int = 0,
    details: dict[str, Any] | None = None,
    fatal: bool | None = None,
) -> CellvisionError:
    """Rebuild the exception for a wire code received in an ERROR message.

    ``fatal`` is the ERROR's own flag: when given it wins over the table (the peer closes the
    connection after a fatal ERROR). An unknown code is non-fatal unless the peer said fatal.
    """
    try:
        cls = ERROR_CLASSES[ErrorCode(code)]
    except ValueError:
        return UnknownErrorCode(
            message,
            wire_code=code,
            peer_fatal=bool(fatal),
            request_id=request_id,
            details=details,
        )
    exc = cls(message, request_id=request_id, details=details)
    if fatal is not None and fatal != exc.fatal:
        exc._fatal = fatal
    return exc


class LocalProtocolError(Exception):
    """Our own code tried to do something the protocol does not allow (a bug on this side)."""


class TooLargeToSend(LocalProtocolError):
    """A frame is larger than the peer accepts (its HELLO's ``max_frame_bytes``): nothing was
    sent and the connection's state is unchanged, so another answer may be sent instead."""

    def __init__(self, message: str, size: int, max_size: int) -> None:
        super().__init__(message)
        self.size = size
        """The frame's size in bytes."""
        self.max_size = max_size
