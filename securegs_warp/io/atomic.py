"""Atomic file writes: a file either keeps its old content or has the complete new content.

Every file securegs-warp writes goes through here. The bytes go to a temporary file in the target's
own folder (so that the final rename stays on one file system), are flushed and fsynced, and only
then replace the target with ``os.replace``. A writer that raises, or a crash, leaves the target as
it was and no half-written file under the target's name.
"""

from __future__ import annotations

import contextlib
import os
import uuid
from pathlib import Path
from typing import BinaryIO, Callable, Iterator


@contextlib.contextmanager
def atomic_open(path: str | os.PathLike) -> Iterator[BinaryIO]:
    """Open ``path`` for binary writing; the content appears under ``path`` only on a clean exit.

    The parent folder must exist. On an exception inside the ``with`` block the temporary file is
    removed and the exception propagates; ``path`` is untouched.
    """
    path = Path(path)
    tmp = path.with_name(f".{path.name}.{uuid.uuid4().hex}.tmp")
    # os.open with mode 0o666 lets the process umask decide the permissions, exactly as open(path,
    # "wb") would; tempfile would create the file 0o600 and the result would stay private.
    fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL | getattr(os, "O_BINARY", 0), 0o666)
    try:
        with os.fdopen(fd, "wb") as f:
            yield f
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            os.unlink(tmp)
        raise
    _fsync_folder(path.parent)


def atomic_write(path: str | os.PathLike, writer: Callable[[BinaryIO], None]) -> None:
    """Call ``writer(f)`` with a binary file object and publish what it wrote at ``path`` atomically."""
    with atomic_open(path) as f:
        writer(f)


def _fsync_folder(folder: Path) -> None:
    """Make the rename itself durable; folders cannot be opened for fsync on Windows."""
    if os.name != "posix":
        return
    fd = os.open(folder, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)
