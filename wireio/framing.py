"""Where the byte stream is, frame by frame: how many bytes the next read may take.

The stream reads the start of each frame on its own (by default exactly its 24-byte header), so
that the :class:`protocol.Connection` parses and admits the header before the body arrives; the
body is then read straight into the buffer the connection gives it (no copy), and no read of a
body takes bytes of the next frame along. This module only counts bytes and reads the body
length from each header; every check of a header is the connection's.
"""

from __future__ import annotations

from protocol.constants import HEADER, HEADER_SIZE, MAGIC


class FrameCursor:
    """Follows one direction of a byte stream through its frames.

    :meth:`want` says how many bytes the next read may take; :meth:`advance` takes the bytes
    read and says whether they completed a header (the owner must then look before more is
    read). ``lookahead`` (bytes, >= 24) is what a read that starts a frame may take:
    24 reads the header alone; more lets a small frame (PING, LIST_INSPECTIONS) arrive in one
    read, at the price of the body bytes that come with a large frame's header being copied on
    their way into its body. After bytes that are not a frame header (bad magic) the cursor
    stops following the stream (``lost``); the connection raises a fatal error for it anyway.
    """

    def __init__(self, lookahead: int = HEADER_SIZE) -> None:
        if lookahead < HEADER_SIZE:
            raise ValueError(f"lookahead must be at least {HEADER_SIZE} bytes, got {lookahead}")
        self.lookahead = lookahead
        self._header = bytearray()
        self._body_left: int | None = None
        """Body bytes still to come of the current frame; None while a header is read."""
        self.lost = False
        """True once the stream was seen not to be framed (bad magic)."""
        self.frames = 0
        """Frames completed so far."""

    @property
    def between_frames(self) -> bool:
        """True when the next byte starts a frame."""
        return not self._header and self._body_left is None

    def want(self, limit: int) -> int:
        """How many bytes (at most ``limit``, which must be > 0) the next read should take."""
        if self.lost:
            return limit
        if self._body_left is None:
            return min(limit, max(HEADER_SIZE - len(self._header), self.lookahead))
        return min(limit, self._body_left)

    def advance(self, data: memoryview) -> bool:
        """Take ``data``, the bytes just read. True when they completed a header (or showed
        that the stream is not framed): the owner must see it, and admit the frame, before its
        body is read. The end of a body needs no such stop: the next read is a header."""
        header_done = False
        view = data
        while len(view) and not self.lost:
            if self._body_left is None:
                need = HEADER_SIZE - len(self._header)
                self._header += view[:need]
                view = view[need:]
                if len(self._header) < HEADER_SIZE:
                    break
                fields = HEADER.unpack_from(self._header)
                self._header.clear()
                if fields[0] != MAGIC:
                    self.lost = True
                    break
                header_done = True
                self._body_left = int(fields[-1])
            else:
                taken = min(self._body_left, len(view))
                self._body_left -= taken
                view = view[taken:]
            if self._body_left == 0:
                self._body_left = None
                self.frames += 1
        return header_done or self.lost


__all__ = ["FrameCursor"]
