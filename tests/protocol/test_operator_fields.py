"""Protocol 1.1's fields for named operators (SPEC §6.3, §6.6): RESULT and OPERATOR_CALL
``result_id``, OPERATOR_ANSWER ``operator`` and ``reason``: on the wire, refused when wrong,
and described by the message schemas."""

from __future__ import annotations

import pytest

from protocol import BadMetadata, OperatorAnswer, OperatorCall, Result, schema
from protocol.frames import Frame, FrameDecoder
from protocol.messages import DecodeContext, message_from_frame

CTX = DecodeContext(max_image_pixels=4096 * 4096)


def wire(message: object) -> Frame:
    decoder = FrameDecoder()
    decoder.feed(message.to_frame((1, 1)).serialize())  # type: ignore[attr-defined]
    frame = decoder.next_frame()
    assert frame is not None
    return frame


def test_the_new_fields_go_over_the_wire_and_validate() -> None:
    answer = OperatorAnswer(
        4, "continue", "anna (console 10.0.0.31:51022)", 1.5, "cosmetic", "anna"
    )
    frame = wire(answer)
    assert frame.metadata["operator"] == "anna"
    assert frame.metadata["reason"] == "cosmetic"
    schema.validate_metadata(frame.type, frame.metadata)
    assert message_from_frame(frame, CTX) == answer
    call = OperatorCall(5, "look", result_id=118)
    frame = wire(call)
    assert frame.metadata["result_id"] == 118
    schema.validate_metadata(frame.type, frame.metadata)
    assert message_from_frame(frame, CTX) == call
    result = Result(6, "magnet_check", False, stored=True, result_id=118)
    frame = wire(result)
    assert frame.metadata["result_id"] == 118
    schema.validate_metadata(frame.type, frame.metadata)
    assert message_from_frame(frame, CTX) == result


def test_absent_fields_stay_absent() -> None:
    assert set(wire(OperatorAnswer(4, "retry")).metadata) == {"choice"}
    assert "result_id" not in wire(OperatorCall(5, "look")).metadata
    assert "result_id" not in wire(Result(6, "x", True)).metadata


@pytest.mark.parametrize("value", [0, -3, "12", 1.5, True])
def test_a_result_id_that_is_no_row_id_is_bad_metadata(value: object) -> None:
    frame = wire(OperatorCall(5, "look"))
    bad = Frame(frame.type, frame.request_id, {**frame.metadata, "result_id": value}, ())
    with pytest.raises(BadMetadata, match="result_id"):
        message_from_frame(bad, CTX)
    with pytest.raises(ValueError, match="result_id"):
        OperatorCall(5, "look", result_id=0)


def test_a_reason_that_is_not_a_string_is_bad_metadata() -> None:
    frame = wire(OperatorAnswer(4, "retry"))
    bad = Frame(frame.type, frame.request_id, {**frame.metadata, "reason": 5}, ())
    with pytest.raises(BadMetadata, match="reason"):
        message_from_frame(bad, CTX)
