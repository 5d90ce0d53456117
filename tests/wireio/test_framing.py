"""FrameCursor: where a byte stream is, frame by frame, however the reads cut it."""

from __future__ import annotations

import random

import pytest

from protocol import Ping
from protocol.frames import Frame
from wireio import FrameCursor


def _frame(body: int) -> bytes:
    return Frame(type=0x0003, request_id=1, blobs=(b"x" * body,)).serialize()


def test_a_read_ending_inside_a_body_whose_header_it_carries_stops_at_the_body() -> None:
    frame = _frame(1000)
    cursor = FrameCursor()
    assert cursor.advance(memoryview(frame[:100])) == 24
    assert cursor.body_left == len(frame) - 100
    # The rest of that body is handed on as it comes.
    assert cursor.advance(memoryview(frame[100:500])) == 400
    assert cursor.advance(memoryview(frame[500:])) == len(frame) - 500
    assert (cursor.body_left, cursor.frames) == (0, 1)


def test_whole_frames_and_a_split_header_are_handed_on_at_once() -> None:
    small = Ping(1, "a").to_frame((1, 0)).serialize()
    data = small + small + _frame(50)[:10]
    cursor = FrameCursor()
    assert cursor.advance(memoryview(data)) == len(data)
    assert cursor.frames == 2
    # The header completes in the next read, which also starts its body.
    rest = _frame(50)[10:40]
    assert cursor.advance(memoryview(rest)) == 14
    assert cursor.body_left == len(_frame(50)) - 40


@pytest.mark.parametrize("seed", range(20))
def test_any_cut_of_a_stream_is_followed_to_the_same_frames(seed: int) -> None:
    rng = random.Random(seed)
    frames = [_frame(rng.choice([0, 1, 7, 300, 5000])) for _ in range(12)]
    stream = b"".join(frames)
    cursor = FrameCursor()
    offset = 0
    while offset < len(stream):
        size = rng.randint(1, 3000)
        ready = cursor.advance(memoryview(stream[offset : offset + size]))
        assert 0 <= ready <= min(size, len(stream) - offset)
        offset += size
    assert cursor.frames == len(frames)
    assert cursor.body_left == 0


def test_bytes_that_are_no_frame_stop_the_following() -> None:
    cursor = FrameCursor()
    junk = memoryview(b"GET / HTTP/1.1\r\nHost: x\r\n\r\n")
    assert cursor.advance(junk) == len(junk)
    assert cursor.lost
    assert cursor.advance(memoryview(b"more")) == 4
