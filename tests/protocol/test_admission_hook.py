"""The connection's admission hooks (server side): ``check_header`` before any body byte,
``admit`` with the metadata before the blobs, and PAUSED when the owner defers a frame."""

from __future__ import annotations

from typing import Any

import numpy as np
import pytest

from protocol import (
    NEED_DATA,
    PAUSED,
    AdmitLater,
    Busy,
    Connection,
    Hello,
    Inspect,
    Ping,
    Role,
    Welcome,
    payload_from_array,
)
from protocol.constants import HEADER_SIZE, MessageType
from protocol.frames import Header, encode_metadata


class Owner:
    def __init__(self) -> None:
        self.headers: list[int] = []
        self.admitted: list[tuple[int, dict[str, Any]]] = []
        self.answer: str = "yes"

    def check_header(self, header: Header) -> None:
        if header.type == MessageType.INSPECT:
            self.headers.append(header.request_id)

    def admit(self, header: Header, metadata: dict[str, Any]) -> None:
        if header.type != MessageType.INSPECT:
            return
        if self.answer == "later":
            raise AdmitLater
        if self.answer == "busy":
            raise Busy("no", request_id=header.request_id)
        self.admitted.append((header.request_id, metadata))


def open_server(owner: Owner) -> Connection:
    server = Connection(Role.SERVER, check_header=owner.check_header, admit=owner.admit)
    client = Connection(Role.CLIENT)
    server.receive_data(client.send(Hello(1, ((1, 1),))))
    hello = server.next_event()
    assert isinstance(hello, Hello)
    server.send(Welcome(1, (1, 1), "s", "0", {}, (), ()))
    return server


def inspect_bytes(rid: int) -> tuple[bytes, int]:
    image = payload_from_array(np.arange(64 * 48, dtype=np.uint8).reshape(48, 64) % 251)
    frame = Inspect(rid, "check", (image,)).to_frame((1, 1))
    data = frame.serialize()
    return data, HEADER_SIZE + len(encode_metadata(frame.metadata))


def test_admit_sees_the_metadata_before_the_blobs_arrive() -> None:
    owner = Owner()
    server = open_server(owner)
    data, up_to_metadata = inspect_bytes(2)
    server.receive_data(data[:up_to_metadata])
    assert server.next_event() is NEED_DATA
    assert owner.headers == [2]
    assert owner.admitted == [(2, owner.admitted[0][1])]
    assert owner.admitted[0][1]["inspection"] == "check"
    server.receive_data(data[up_to_metadata:])
    message = server.next_event()
    assert isinstance(message, Inspect)
    assert message.inspection == "check"


def test_a_deferred_frame_pauses_until_it_is_admitted() -> None:
    owner = Owner()
    owner.answer = "later"
    server = open_server(owner)
    data, _ = inspect_bytes(2)
    server.receive_data(data)
    assert server.next_event() is PAUSED
    assert server.next_event() is PAUSED  # asked again, still deferred
    assert server.buffered_bytes == len(data)  # nothing dropped while paused
    owner.answer = "yes"
    message = server.next_event()
    assert isinstance(message, Inspect)
    assert owner.headers == [2]  # the header was checked once


def test_a_frame_refused_with_its_metadata_is_skipped_and_the_stream_goes_on() -> None:
    owner = Owner()
    owner.answer = "busy"
    server = open_server(owner)
    data, up_to_metadata = inspect_bytes(2)
    server.receive_data(data[:up_to_metadata])
    with pytest.raises(Busy):
        server.next_event()
    assert 2 in server.pending  # an ERROR is owed for it
    owner.answer = "yes"
    server.receive_data(data[up_to_metadata:])
    server.receive_data(Ping(3, "after").to_frame((1, 1)).serialize())
    event = server.next_event()
    assert isinstance(event, Ping)
    assert event.data == "after"
    assert server.buffered_bytes == 0
