"""Where the byte stream is, frame by frame, so that a frame's body can be read straight into
the buffer the connection makes for it.

A read between frames takes whatever has arrived (small frames come many at a time). A frame's
header, metadata and blob table (its *prefix*: what the connection admits a frame by, SPEC
§3.1) go to the :class:`protocol.Connection` as they come. When a read ends inside the blobs of
a frame whose prefix it carried, the blobs' first bytes are held back until the connection has
admitted the frame; then they are copied once into the new body buffer, and the rest is read
into it directly. This module only counts bytes and reads the lengths from each header; every
check of a header is the connection's.
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
        self._prefix_left = 0
        """Metadata and blob-table bytes still to come of the current frame."""
        self._body_left: int | None = None
        """Blob bytes still to come of the current frame (after its prefix); None between
        frames or in a header."""
        self.lost = False
        """True once the stream was seen not to be framed (bad magic)."""
        self.frames = 0
        """Frames completed so far."""

    @property
    def body_left(self) -> int:
        """Blob bytes still to come of the frame being received, once its prefix has come (0
        between frames, in a header or in a prefix)."""
        return 0 if self._prefix_left else self._body_left or 0

    def advance(self, data: memoryview) -> int:
        """Take ``data``, the bytes just read; how many of its first bytes may go to the
        connection now. That is all of them, unless they end inside the blobs of a frame whose
        prefix they carry: then the offset where those blobs start (the rest waits for the
        frame to be admitted, so that it is copied into the body once, not buffered first)."""
        offset, end = 0, len(data)
        blobs_start: int | None = None
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
                blob_count, metadata_length, body_length = fields[5], fields[7], fields[8]
                self._prefix_left = min(metadata_length + 4 * blob_count, body_length)
                self._body_left = body_length - self._prefix_left
                blobs_start = None
                if not self._prefix_left:
                    blobs_start = offset
            elif self._prefix_left:
                taken = min(self._prefix_left, end - offset)
                self._prefix_left -= taken
                offset += taken
                if not self._prefix_left:
                    blobs_start = offset
            else:
                taken = min(self._body_left, end - offset)
                self._body_left -= taken
                offset += taken
            if self._body_left == 0 and not self._prefix_left:
                self._body_left = None
                self.frames += 1
                blobs_start = None
        if self._body_left is not None and blobs_start is not None and not self.lost:
            return blobs_start
        return end


__all__ = ["FrameCursor"]
