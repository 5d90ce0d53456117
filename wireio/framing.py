"""Where the byte stream is, frame by frame, so that a frame's body can be read straight into
the buffer the connection makes for it.

A read between frames takes whatever has arrived (small frames come many at a time). When it
ends inside the body of a frame whose header it carried, that body's first bytes are held back
until the :class:`protocol.Connection` has parsed and admitted the header; then they are copied
once into the new body buffer, and the rest of the body is read into it directly. This module
only counts bytes and reads the body length from each header; every check of a header is the
connection's.
"""

from __future__ import annotations

from protocol.constants import HEADER, HEADER_SIZE, MAGIC


class FrameCursor:
    """Follows one direction of a byte stream through its frames.

    After bytes that are not a frame header (bad magic) the cursor stops following the stream
    (``lost``): everything is then handed on at once, and the connection raises a fatal error.
    """

    def __init__(self) -> None:
        self._header = bytearray()
        self._body_left: int | None = None
        """Body bytes still to come of the current frame; None between frames or in a header."""
        self.lost = False
        """True once the stream was seen not to be framed (bad magic)."""
        self.frames = 0
        """Frames completed so far."""

    @property
    def body_left(self) -> int:
        """Bytes still to come of the body being received (0 between frames or in a header)."""
        return self._body_left or 0

    def advance(self, data: memoryview) -> int:
        """Take ``data``, the bytes just read; how many of its first bytes may go to the
        connection now. That is all of them, unless they end inside a body whose header they
        carry: then the offset where that body starts (the rest waits for the header to be
        admitted, so that it is copied into the body once, not buffered first)."""
        offset, end = 0, len(data)
        body_start: int | None = None
        while offset < end and not self.lost:
            if self._body_left is None:
                piece = data[offset : offset + HEADER_SIZE - len(self._header)]
                self._header += piece
                offset += len(piece)
                if len(self._header) < HEADER_SIZE:
                    break
                fields = HEADER.unpack_from(self._header)
                self._header.clear()
                if fields[0] != MAGIC:
                    self.lost = True
                    break
                self._body_left = int(fields[-1])
                body_start = offset
            else:
                taken = min(self._body_left, end - offset)
                self._body_left -= taken
                offset += taken
            if self._body_left == 0:
                self._body_left = None
                self.frames += 1
                body_start = None
        if self._body_left is not None and body_start is not None and not self.lost:
            return body_start
        return end


__all__ = ["FrameCursor"]
