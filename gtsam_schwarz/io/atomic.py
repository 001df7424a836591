"""Atomic file output: a failure or an interrupt never leaves a truncated or half-written file."""

from __future__ import annotations

import contextlib
import os
import secrets
import stat
from typing import Iterable


def atomic_write(path, data: bytes | str | Iterable[str], *, parents: bool = False) -> str:
    """Write ``data`` (bytes, text, or an iterable of text lines) to a temporary file beside ``path``,
    fsync it, then ``os.replace`` it into place; the destination is untouched on any error.

    A symlink is followed (the file it points to is replaced, keeping its mode); ``parents=True``
    creates missing folders. Raises ``OSError`` (``IsADirectoryError`` for a folder)."""
    target = os.path.realpath(os.fspath(path))
    directory, name = os.path.split(target)
    if os.path.isdir(target):
        raise IsADirectoryError(f"{path} is a directory")
    if parents:
        os.makedirs(directory, exist_ok=True)
    tmp = os.path.join(directory, f".{name}.{os.getpid()}.{secrets.token_hex(4)}.tmp")
    fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o666)
    try:
        with os.fdopen(fd, "wb") as fh:
            if isinstance(data, (bytes, str)):
                fh.write(data.encode("utf-8") if isinstance(data, str) else data)
            else:
                fh.writelines(line.encode("utf-8") for line in data)
            fh.flush()
            os.fsync(fh.fileno())
        try:  # keep the mode of the file replaced; a new file gets the umask's default
            os.chmod(tmp, stat.S_IMODE(os.stat(target).st_mode))
        except FileNotFoundError:
            umask = os.umask(0)
            os.umask(umask)
            os.chmod(tmp, 0o666 & ~umask)
        os.replace(tmp, target)
    except BaseException:  # also KeyboardInterrupt: never leave the temporary file behind
        with contextlib.suppress(OSError):
            os.unlink(tmp)
        raise
    with contextlib.suppress(OSError):  # make the rename durable (best effort; not all systems allow it)
        dir_fd = os.open(directory, os.O_RDONLY)
        try:
            os.fsync(dir_fd)
        finally:
            os.close(dir_fd)
    return os.fspath(path)
