"""Atomic writes: a file, or a whole folder, either keeps its old content or has the complete new one.

Every file securegs-warp writes goes through here. The bytes go to a temporary file in the target's
own folder (so that the final rename stays on one file system), are flushed and fsynced, and only
then replace the target with ``os.replace``. A writer that raises, or a crash, leaves the target as
it was and no half-written file under the target's name.

A folder whose files only make sense together (a model: point cloud + MLPs) is written with
:func:`atomic_folder`: it is built under a hidden sibling name and swapped in whole, so that no
reader ever sees new files beside old ones.
"""

from __future__ import annotations

import contextlib
import ctypes
import errno
import os
import re
import shutil
import stat
import sys
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


def save_figure(fig, path: str | os.PathLike, dpi: int) -> None:
    """A matplotlib figure at ``path``, atomically, in the format its suffix names (PNG without one),
    then closed (pyplot keeps every open figure alive). A file object carries no name, so the format
    is passed explicitly."""
    import matplotlib.pyplot as plt  # only a caller that drew a figure has matplotlib

    atomic_write(path, lambda f: fig.savefig(f, format=Path(path).suffix[1:].lower() or "png", dpi=dpi))
    plt.close(fig)


@contextlib.contextmanager
def atomic_folder(path: str | os.PathLike) -> Iterator[Path]:
    """Build a folder's content in a new hidden folder; on a clean exit it replaces ``path`` whole.

    Yields the new folder, ``<parent>/.<name>.tmp-<uuid>``, which starts empty: write every file
    the folder must hold into it. On a clean exit its files and the folder are fsynced and it is
    published under ``path``, replacing the folder there (and whatever that folder held) as one
    unit, and the old folder is deleted. Where the file system can swap two names atomically (Linux
    ``renameat2(RENAME_EXCHANGE)``; ext4, xfs, btrfs, tmpfs) ``path`` always names a complete
    folder, old or new; elsewhere the old folder is renamed aside to ``.<name>.old-<uuid>`` first,
    and a crash between the two renames leaves ``path`` absent with the complete old folder under
    that hidden name. On an exception the new folder is removed and ``path`` is untouched.

    A crash can leave hidden ``.<name>.tmp-*`` / ``.<name>.old-*`` siblings; the next successful
    ``atomic_folder`` of the same ``path`` removes them, after publishing (never before: such a
    leftover may hold the only complete copy). One writer per ``path`` at a time: a second one's
    clean-up can remove the first one's folder under construction, which then fails loudly.

    The parent is created if needed. A symbolic link at ``path`` is kept and the folder it points
    to is replaced. The replaced folder keeps its permission bits. A process whose working folder
    is ``path`` is left in the deleted old folder.

    Raises:
        NotADirectoryError: ``path`` exists and is not a folder.
    """
    # realpath: "." or "x/.." have no usable name, and a link's target is what readers open.
    path = Path(os.path.realpath(path))
    parent = path.parent
    parent.mkdir(parents=True, exist_ok=True)
    if path.exists() and not path.is_dir():
        raise NotADirectoryError(errno.ENOTDIR, "exists and is not a folder", os.fspath(path))
    tmp = parent / f".{path.name}.tmp-{uuid.uuid4().hex}"
    os.mkdir(tmp)
    try:
        yield tmp
        # After the writes: the replaced folder may be read-only to its owner.
        with contextlib.suppress(FileNotFoundError):
            os.chmod(tmp, stat.S_IMODE(path.stat().st_mode))
        _fsync_tree(tmp)
        old = _publish_folder(tmp, path)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    if old is not None:
        shutil.rmtree(old, ignore_errors=True)
    remove_folder_leftovers(path)
    _fsync_folder(parent)


def folder_leftovers(path: str | os.PathLike) -> list[Path]:
    """The hidden siblings an interrupted :func:`atomic_folder` of ``path`` can leave behind."""
    path = Path(os.path.realpath(path))
    pattern = re.compile(rf"\.{re.escape(path.name)}\.(tmp|old)-[0-9a-f]{{32}}")
    try:
        names = os.listdir(path.parent)
    except FileNotFoundError:
        return []
    return sorted(path.parent / name for name in names if pattern.fullmatch(name))


def remove_folder_leftovers(path: str | os.PathLike) -> None:
    """Delete what :func:`folder_leftovers` lists (best effort: a leftover that resists stays hidden)."""
    for leftover in folder_leftovers(path):
        shutil.rmtree(leftover, ignore_errors=True)


def _publish_folder(new: Path, path: Path) -> Path | None:
    """Put folder ``new`` under ``path``; returns where the replaced folder now is (None if none)."""
    if not path.exists():
        os.rename(new, path)
        _fsync_folder(path.parent)
        return None
    if _exchange(new, path):
        # ``new`` now names the old folder.
        _fsync_folder(path.parent)
        return new
    old = path.with_name(f".{path.name}.old-{uuid.uuid4().hex}")
    os.rename(path, old)
    try:
        os.rename(new, path)
    except BaseException:
        os.rename(old, path)
        raise
    _fsync_folder(path.parent)
    return old


_AT_FDCWD = -100
_RENAME_EXCHANGE = 2
_NOT_SUPPORTED = {errno.EINVAL, errno.ENOSYS, errno.EOPNOTSUPP, errno.ENOTSUP}


def _exchange(a: Path, b: Path) -> bool:
    """Swap the names ``a`` and ``b`` in one atomic step; False where the system cannot."""
    renameat2 = _renameat2()
    if renameat2 is None:
        return False
    if renameat2(_AT_FDCWD, os.fsencode(a), _AT_FDCWD, os.fsencode(b), _RENAME_EXCHANGE) == 0:
        return True
    err = ctypes.get_errno()
    if err in _NOT_SUPPORTED:
        return False
    raise OSError(err, os.strerror(err), os.fspath(a), None, os.fspath(b))


def _renameat2():
    if not sys.platform.startswith("linux"):
        return None
    try:
        function = ctypes.CDLL(None, use_errno=True).renameat2  # glibc >= 2.28
    except (OSError, AttributeError):
        return None
    function.argtypes = [ctypes.c_int, ctypes.c_char_p, ctypes.c_int, ctypes.c_char_p, ctypes.c_uint]
    function.restype = ctypes.c_int
    return function


def _fsync_tree(folder: Path) -> None:
    """fsync every file under ``folder`` and every folder, so that a published folder is on disk."""
    if os.name != "posix":
        return
    for root, _dirs, files in os.walk(folder):
        for name in files:
            fd = os.open(os.path.join(root, name), os.O_RDONLY)
            try:
                os.fsync(fd)
            finally:
                os.close(fd)
        _fsync_folder(Path(root))


def _fsync_folder(folder: Path) -> None:
    """Make the rename itself durable; folders cannot be opened for fsync on Windows."""
    if os.name != "posix":
        return
    fd = os.open(folder, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)
