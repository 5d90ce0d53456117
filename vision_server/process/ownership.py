"""Files one running server owns: a spool, a certificate store. Two servers whose configurations
sit in one folder would otherwise share their defaults and take each other's rows (an SQLite
spool's sequence numbers collide; a certificate store is made again for the other's name).

:func:`claim` takes an exclusive ``flock`` on ``PATH.lock`` for as long as the process holds the
returned :class:`Claim` (the kernel lets it go when the process ends, however it ends).
"""

from __future__ import annotations

import contextlib
import fcntl
import os
from pathlib import Path


class Claimed(Exception):
    """Another running process owns the file (names it and what it is)."""


class Claim:
    """An exclusive lock on ``path`` + ``.lock``; :meth:`release` gives it back (once)."""

    def __init__(self, path: Path, what: str) -> None:
        self.lock_path = path.with_name(path.name + ".lock")
        self.lock_path.parent.mkdir(parents=True, exist_ok=True)
        self._fd: int | None = os.open(self.lock_path, os.O_RDWR | os.O_CREAT, 0o600)
        try:
            fcntl.flock(self._fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            os.close(self._fd)
            self._fd = None
            raise Claimed(
                f"{what} {path} is in use by another running server (its lock "
                f"{self.lock_path} is held): give each server its own"
            ) from None

    def release(self) -> None:
        if self._fd is not None:
            with contextlib.suppress(OSError):
                fcntl.flock(self._fd, fcntl.LOCK_UN)
                os.close(self._fd)
            self._fd = None


def claim(path: Path, what: str) -> Claim:
    """Own ``path`` (a file or folder) for this process, or raise :class:`Claimed`."""
    return Claim(Path(path), what)


__all__ = ["Claim", "Claimed", "claim"]
