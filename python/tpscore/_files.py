"""Reading and writing files safely: bounded reads and atomic writes.

Every reader in tpscore reads through :func:`read_limited`, which never reads more than
a limit the format sets (a forged header or an endless stream such as ``/dev/zero``
cannot make it allocate without bound), and every writer writes through
:func:`atomic_write`, which leaves either the old file or the whole new one, never a
part (a full disk or an interrupted process leaves nothing half-written). Errors name
the file.
"""
from __future__ import annotations

import errno
import os
import secrets
import stat
from pathlib import Path

from ._validation import as_path

__all__ = ["atomic_write", "check_readable", "open_for_reading", "read_bytes", "read_limited",
           "regular_file_size", "MAX_TEXT_FILE_BYTES"]

#: The largest landmark or other small text file read (16 MiB): a landmark file holds
#: a few kilobytes.
MAX_TEXT_FILE_BYTES = 16 * 2**20


def check_readable(path, name: str = "path") -> Path:
    """The path of an existing regular file (or a stream such as a pipe), or a
    ValueError that says what is there instead."""
    text = as_path(path, name)
    where = repr(text)
    if os.path.isdir(text):
        raise ValueError(f"{where}: is a folder, not a file")
    if not os.path.exists(text):
        folder = os.path.dirname(text)
        if folder and not os.path.isdir(folder):
            raise ValueError(f"{where}: file not found (the folder {folder!r} does not exist)")
        raise ValueError(f"{where}: file not found")
    return Path(text)


def open_for_reading(path, name: str = "path"):
    """An open binary file handle; ValueError naming the file if it cannot be opened."""
    checked = check_readable(path, name)
    try:
        return open(checked, "rb")
    except OSError as exc:
        raise ValueError(f"{str(checked)!r}: cannot be read ({exc.strerror or exc})") from None


def regular_file_size(handle) -> int | None:
    """The size of an open regular file, or None for a stream (a pipe, a device)."""
    status = os.fstat(handle.fileno())
    return status.st_size if stat.S_ISREG(status.st_mode) else None


def read_limited(handle, count: int, where: str) -> bytes:
    """Read up to `count` bytes from an open file: fewer only at its end.

    A stream is read in pieces, so an endless one (``/dev/zero``) costs no more than
    `count` bytes of memory.
    """
    pieces = []
    left = count
    try:
        while left > 0:
            piece = handle.read(min(left, 2**24))
            if not piece:
                break
            pieces.append(piece)
            left -= len(piece)
    except OSError as exc:
        raise ValueError(f"{where}: cannot be read ({exc.strerror or exc})") from None
    return b"".join(pieces)


def read_bytes(path, limit: int, what: str, name: str = "path") -> bytes:
    """The whole content of a file of at most `limit` bytes; ValueError naming the
    file if it is missing, a folder, unreadable or longer (judged from its size before
    reading when it is a regular file, after `limit` + 1 bytes when it is a stream)."""
    with open_for_reading(path, name) as handle:
        where = repr(str(handle.name))
        size = regular_file_size(handle)
        if size is not None and size > limit:
            raise ValueError(f"{where}: the file is {size:,} bytes; {what} has at most {limit:,}")
        data = read_limited(handle, limit + 1, where)
    if len(data) > limit:
        raise ValueError(f"{where}: longer than the {limit:,} bytes {what} has at most")
    return data


def _create_temporary(folder: Path, name: str) -> tuple[int, str]:
    """A new, empty temporary file beside the target: (descriptor, path).

    Created with mode 0o666 less the umask, as open() would create the target itself
    (tempfile.mkstemp's 0o600 would leave every written file private).
    """
    for _ in range(100):
        path = folder / f".{name}.{secrets.token_hex(6)}.tmp"
        try:
            return os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL | getattr(os, "O_BINARY", 0), 0o666), str(path)
        except FileExistsError:
            continue
    raise FileExistsError(errno.EEXIST, f"no free temporary file name in {str(folder)!r}")


def _current_umask() -> int:
    # the umask can only be read by setting it; done once, at import, before any of
    # tpscore's writes
    mask = os.umask(0o022)
    os.umask(mask)
    return mask


_UMASK = _current_umask()


def atomic_write(path, data: bytes, name: str = "path") -> None:
    """Write `data` to `path` through a temporary file in the same folder, then rename.

    The rename is atomic on POSIX and Windows, so a reader never sees a partial file
    and a failed write (a full disk, a file-size limit) leaves the previous file (if
    any) untouched and no temporary file behind.

    Raises
    ------
    ValueError
        The folder does not exist, or `path` is a folder.
    OSError
        The system refused the write; the message names `path`.
    """
    target = Path(as_path(path, name))
    where = repr(str(target))
    folder = target.parent if str(target.parent) else Path(".")
    if not folder.is_dir():
        raise ValueError(f"cannot write {where}: the folder {str(folder)!r} does not exist")
    if target.is_dir():
        raise ValueError(f"cannot write {where}: it is a folder")
    try:
        handle, tmp_name = _create_temporary(folder, target.name)
    except OSError as exc:
        raise OSError(exc.errno, f"cannot write {where}: {exc.strerror or exc}") from None
    try:
        with os.fdopen(handle, "wb") as fh:
            fh.write(data)
        # a temporary file is private (0600); the result gets the permissions open()
        # would have given it, so others can read a page or a mesh as usual
        os.chmod(tmp_name, 0o666 & ~_UMASK)
        os.replace(tmp_name, target)
    except BaseException as exc:
        try:
            os.unlink(tmp_name)
        except OSError:
            pass
        if isinstance(exc, OSError):
            raise OSError(exc.errno, f"cannot write {where}: {exc.strerror or exc}") from None
        raise
