"""Atomic file writes: a reader (or a Ctrl-C) never sees a half-written result.

Data goes to a temporary file in the destination's folder, is flushed and
``fsync``-ed, and is moved over the destination with :func:`os.replace` (atomic on
POSIX); the folder is then ``fsync``-ed so the rename itself is durable. On any
error, ``KeyboardInterrupt`` included, the temporary file is removed and the
previous destination file is left untouched.
"""

from __future__ import annotations

import contextlib
import os
import tempfile
from pathlib import Path


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


def _fsync_directory(directory: Path) -> None:
    # Not every platform can open a directory for fsync; durability is best effort there.
    try:
        fd = os.open(directory, os.O_RDONLY)
    except OSError:
        return
    try:
        with contextlib.suppress(OSError):
            os.fsync(fd)
    finally:
        os.close(fd)


def write_bytes_atomic(path: str | os.PathLike[str], data: bytes) -> Path:
    """Write ``data`` to ``path`` atomically; return the path.

    Raises
    ------
    OSError
        If the file cannot be written; the destination is then unchanged.
    """
    destination = Path(path)
    directory = destination.parent if str(destination.parent) else Path(".")
    fd, temp_name = tempfile.mkstemp(prefix=f".{destination.name}.", suffix=".tmp", dir=directory)
    try:
        os.fchmod(fd, 0o666 & ~_umask())  # mkstemp makes 0600 files; honour the umask
        with os.fdopen(fd, "wb") as handle:
            handle.write(data)
            handle.flush()
            os.fsync(handle.fileno())
        os.replace(temp_name, destination)
    except BaseException:
        with contextlib.suppress(OSError):
            os.unlink(temp_name)
        raise
    _fsync_directory(directory)
    return destination
