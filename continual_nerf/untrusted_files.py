"""Reading files another process controls (a capture folder): only regular files, and only inside their folder.

Opening a FIFO for reading blocks until someone writes to it, and reading a device or a folder does not end or fails
oddly; a path that is absolute, climbs out with `..` or passes through a symlink could make the reader train on any
file the user can read. Both are refused here, each with a one-line DatasetError naming the path.
"""

from __future__ import annotations

import os
import stat
from pathlib import Path
from typing import BinaryIO

from continual_nerf.errors import DatasetError

PROC_FD = Path("/proc/self/fd")
"""Linux's view of this process's open files: where an opened file really is, whatever was renamed meanwhile."""


def real_path_inside(path: Path, folder: Path) -> Path:
    """The real path of `path` (symlinks and `..` resolved), which must lie inside the real path of `folder`."""
    try:
        real = Path(os.path.realpath(path))
    except (OSError, ValueError) as error:  # a NUL byte, a symlink loop
        raise DatasetError(f"{path}: not a usable path ({error})") from None
    if not real.is_relative_to(os.path.realpath(folder)):
        raise DatasetError(f"{path}: lies outside the capture folder {folder} (its real path is {real}); not read")
    return real


def check_regular(path: Path) -> None:
    """A one-line error for a path that is not a regular file (a FIFO would block the reader); missing is an OSError."""
    mode = os.stat(path).st_mode
    if not stat.S_ISREG(mode):
        raise DatasetError(f"{path}: not a regular file ({file_kind(mode)}); not read")


def open_inside(path: Path, folder: Path) -> BinaryIO:
    """`path` opened for reading, if its real path lies inside `folder` and it is a regular file.

    The real path is opened without following a last symlink and without blocking, and the opened file is checked
    again (kind, and on Linux where it really is), so a file swapped in between the check and the open is refused too.
    """
    real = real_path_inside(path, folder)
    descriptor = os.open(real, os.O_RDONLY | os.O_NONBLOCK | os.O_NOFOLLOW)
    try:
        mode = os.fstat(descriptor).st_mode
        if not stat.S_ISREG(mode):
            raise DatasetError(f"{path}: not a regular file ({file_kind(mode)}); not read")
        opened = PROC_FD / str(descriptor)
        if opened.is_symlink():
            real_path_inside(Path(os.readlink(opened)), folder)
    except BaseException:
        os.close(descriptor)
        raise
    return os.fdopen(descriptor, "rb")


def file_kind(mode: int) -> str:
    kinds = {stat.S_ISDIR: "a folder", stat.S_ISFIFO: "a FIFO", stat.S_ISSOCK: "a socket"}
    return next((name for test, name in kinds.items() if test(mode)), "a device")
