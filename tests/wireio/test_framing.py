"""FrameCursor: where a byte stream is, frame by frame, however the reads cut it."""

from __future__ import annotations

import random

import pytest

from protocol import Ping
from protocol.frames import Frame
from wireio import FrameCursor


def _frame(body: int) -> bytes:
    return Frame(type=0x0003, request_id=1, blobs=(b"x" * body,)).serialize()


def _prefix(body: int) -> int:
    """Header, metadata and blob table of :func:`_frame`: what a connection admits it by."""
    frame = Frame(type=0x0003, request_id=1, blobs=(b"x" * body,))
    return len(frame.serialize()) - body


def test_a_read_ending_inside_the_blobs_of_a_frame_it_carries_stops_where_they_start() -> None:
    frame = _frame(1000)
    prefix = _prefix(1000)
    cursor = FrameCursor()
    # Header, metadata and blob table go on (the frame is admitted by them); the blobs wait.
    assert cursor.advance(memoryview(frame[:100])) == prefix
    assert cursor.body_left == len(frame) - 100
    # The rest of the blobs are handed on as they come.
    assert cursor.advance(memoryview(frame[100:500])) == 400
    assert cursor.advance(memoryview(frame[500:])) == len(frame) - 500
    assert (cursor.body_left, cursor.frames) == (0, 1)


def test_a_prefix_split_over_reads_is_handed_on_and_the_blobs_wait() -> None:
    frame = _frame(1000)
    prefix = _prefix(1000)
    cursor = FrameCursor()
    assert cursor.advance(memoryview(frame[:10])) == 10  # half a header
    assert cursor.advance(memoryview(frame[10 : prefix - 2])) == prefix - 12
    assert cursor.body_left == 0  # still in the prefix
    assert cursor.advance(memoryview(frame[prefix - 2 : prefix + 50])) == 2


def test_whole_frames_and_a_split_header_are_handed_on_at_once() -> None:
    small = Ping(1, "a").to_frame((1, 0)).serialize()
    data = small + small + _frame(50)[:10]
    cursor = FrameCursor()
    assert cursor.advance(memoryview(data)) == len(data)
    assert cursor.frames == 2
    # The header completes in the next read, which also carries the prefix and starts the blobs.
    rest = _frame(50)[10:40]
    assert cursor.advance(memoryview(rest)) == _prefix(50) - 10
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
