"""The error taxonomy: one class and one table row per wire code, lossless rebuilding."""

from __future__ import annotations

import pytest

from protocol import (
    ERROR_CLASSES,
    ERROR_TABLE,
    CellvisionError,
    Error,
    ErrorCode,
    ShuttingDown,
    UnknownErrorCode,
    error_from_code,
)


@pytest.mark.parametrize("code", list(ErrorCode))
def test_every_code_has_a_class_and_a_table_row(code: ErrorCode) -> None:
    cls = ERROR_CLASSES[code]
    assert cls.code is code
    assert issubclass(cls, CellvisionError)
    assert ERROR_TABLE[code].meaning
    assert cls("x").fatal is ERROR_TABLE[code].fatal


def test_codes_fit_a_u16_and_are_unique() -> None:
    values = [int(c) for c in ErrorCode]
    assert len(set(values)) == len(values)
    assert all(0 < v <= 0xFFFF for v in values)
    assert set(ERROR_CLASSES) == set(ErrorCode) == set(ERROR_TABLE)


def test_fatal_codes_are_the_documented_ones() -> None:
    # SPEC.md §7 lists exactly these as fatal; SHUTTING_DOWN answers each request, CLOSE follows.
    fatal = {c.name for c, info in ERROR_TABLE.items() if info.fatal}
    assert fatal == {
        "MALFORMED_FRAME",
        "UNSUPPORTED_VERSION",
        "FRAME_TOO_LARGE",
        "DUPLICATE_REQUEST_ID",
        "NOT_AUTHENTICATED",
    }


@pytest.mark.parametrize("code", list(ErrorCode))
def test_error_from_code_round_trip(code: ErrorCode) -> None:
    exc = error_from_code(int(code), "boom", request_id=9, details={"k": 1})
    assert type(exc) is ERROR_CLASSES[code]
    assert (exc.message, exc.request_id, exc.details) == ("boom", 9, {"k": 1})
    assert exc.fatal is ERROR_TABLE[code].fatal


@pytest.mark.parametrize("code", list(ErrorCode))
def test_message_exception_message_round_trip(code: ErrorCode) -> None:
    original = ERROR_CLASSES[code]("it broke", request_id=4, details={"n": [1, 2]})
    message = Error.from_exception(original)
    assert message == Error(4, int(code), "it broke", original.fatal, {"n": [1, 2]})
    assert message.name == code.name
    rebuilt = message.to_exception()
    assert type(rebuilt) is type(original)
    assert (rebuilt.message, rebuilt.request_id, rebuilt.details, rebuilt.fatal) == (
        "it broke",
        4,
        {"n": [1, 2]},
        original.fatal,
    )


def test_from_exception_can_override_the_request_id() -> None:
    assert Error.from_exception(ShuttingDown("bye", request_id=3), request_id=8).request_id == 8


@pytest.mark.parametrize("peer_fatal", [False, True])
def test_unknown_code_takes_the_peers_fatal_flag(peer_fatal: bool) -> None:
    exc = Error(5, 4242, "from the future", peer_fatal).to_exception()
    assert isinstance(exc, UnknownErrorCode)
    assert exc.wire_code == 4242
    assert exc.fatal is peer_fatal
    assert exc.request_id == 5
    assert Error(5, 4242, "x").name == "UNKNOWN_4242"


def test_unknown_code_relays_losslessly() -> None:
    message = Error(5, 4242, "from the future", True, {"a": 1})
    assert Error.from_exception(message.to_exception()) == message


def test_unknown_code_is_non_fatal_by_default() -> None:
    assert error_from_code(999, "x").fatal is False


def test_peer_fatal_flag_wins_over_the_table() -> None:
    # The sender closes the connection after a fatal ERROR whatever our table says.
    assert Error(1, ErrorCode.BUSY, "x", fatal=True).to_exception().fatal is True
    assert Error(1, ErrorCode.MALFORMED_FRAME, "x", fatal=False).to_exception().fatal is False
    # Without the flag the table decides.
    assert error_from_code(ErrorCode.MALFORMED_FRAME, "x").fatal is True


def test_repr_names_the_class_and_request() -> None:
    assert repr(ShuttingDown("bye", request_id=2)) == "ShuttingDown('bye', request_id=2)"
