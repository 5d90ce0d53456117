"""Writing the files beside the configuration (the file itself, its history's versions, the
templates the console trains) so that a crash or a full disk never leaves one half written:
each is written to a temporary file in the same folder, synced, then given its name, and the
folder is synced so that the new name survives a power cut.
"""

from __future__ import annotations

import contextlib
import os
import tempfile
from pathlib import Path


def replace_file(path: Path, data: bytes, *, mode_of: Path | None = None) -> None:
    """Write ``data`` as ``path`` (replacing it), atomically and durably. On any failure the
    temporary file is removed and ``path`` is as it was. The mode is ``mode_of``'s (default
    ``path``'s; a new file keeps the temporary file's, owner only)."""
    tmp = _written(path.parent, f".{path.name}.", data, mode_of or path)
    try:
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
    sync_folder(path.parent)


def write_new(
    path: Path, data: bytes, *, mode_of: Path | None = None, mode: int | None = None
) -> bool:
    """Write ``data`` as ``path`` atomically and durably, never over an existing file: False
    (nothing written) when ``path`` exists, e.g. written meanwhile by another writer. The mode
    is ``mode`` or ``mode_of``'s."""
    tmp = _written(path.parent, ".", data, mode_of, mode)
    try:
        try:
            os.link(tmp, path)  # fails when the name is taken, unlike a rename
        except FileExistsError:
            return False
    finally:
        tmp.unlink(missing_ok=True)
    sync_folder(path.parent)
    return True


def sync_folder(folder: Path) -> None:
    """Make a new name in ``folder`` durable (where the system allows opening a folder)."""
    with contextlib.suppress(OSError):
        fd = os.open(folder, os.O_RDONLY)
        try:
            os.fsync(fd)
        finally:
            os.close(fd)


def _written(
    folder: Path, prefix: str, data: bytes, mode_of: Path | None, mode: int | None = None
) -> Path:
    """A synced temporary file in ``folder`` holding ``data``."""
    fd, name = tempfile.mkstemp(dir=folder, prefix=prefix, suffix=".tmp")
    tmp = Path(name)
    try:
        with os.fdopen(fd, "wb") as out:
            out.write(data)
            out.flush()
            os.fsync(out.fileno())
        if mode is not None:
            os.chmod(tmp, mode)
        elif mode_of is not None:
            with contextlib.suppress(OSError):
                os.chmod(tmp, mode_of.stat().st_mode & 0o777)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
    return tmp


__all__ = ["replace_file", "sync_folder", "write_new"]
