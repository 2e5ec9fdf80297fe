"""Write-then-rename: a file under its final name is always complete, whenever the process is killed.

A write that fails (no space left, a read-only folder) is a one-line OutputError naming the file and the cause, and
leaves the previous file as it was; a temporary file left by a killed process is removed at the next start.
"""

from __future__ import annotations

import contextlib
import errno
import os
import re
from pathlib import Path
from typing import BinaryIO, Callable, List, Optional

from continual_nerf.errors import OutputError

PARTIAL_NAME = re.compile(r"\..+\.partial-(\d+)")
"""Temporary files of write_atomically: `.<final name>.partial-<pid of the writing process>`."""

CAUSES = {
    errno.ENOSPC: "no space left on the device",
    errno.EDQUOT: "disk quota exceeded",
    errno.EROFS: "read-only file system",
    errno.EACCES: "permission denied: the folder is read-only for this user",
    errno.EPERM: "operation not permitted",
}
"""How a failed write's cause is named, by errno; others by the system's own message."""


def write_atomically(path: Path, write: Callable[[BinaryIO], object], temporary_dir: Optional[Path] = None) -> None:
    """Call `write` on a temporary file in `temporary_dir` (default: beside `path`), then rename it to `path`."""
    folder = path.parent if temporary_dir is None else temporary_dir
    temporary = folder / f".{path.name}.partial-{os.getpid()}"
    try:
        folder.mkdir(parents=True, exist_ok=True)
        path.parent.mkdir(parents=True, exist_ok=True)
        with temporary.open("wb") as file:
            write(file)
            file.flush()
            os.fsync(file.fileno())  # the rename must not reach the disk before the data does
        os.replace(temporary, path)
    except (OSError, RuntimeError) as error:
        cause = os_error_of(error)
        if cause is None:
            raise
        raise OutputError(f"{path}: cannot be written ({describe(cause)})") from None
    finally:
        with contextlib.suppress(OSError):  # what cannot be removed now is removed at the next start
            temporary.unlink(missing_ok=True)


def os_error_of(error: Optional[BaseException]) -> Optional[OSError]:
    """`error` if it is an OSError, else the OSError it was raised while handling: torch's zip writer turns a
    failed write of the file into its own RuntimeError."""
    while error is not None and not isinstance(error, OSError):
        error = error.__cause__ or error.__context__
    return error


def describe(error: OSError) -> str:
    return CAUSES.get(error.errno or 0, error.strerror or str(error))


def write_text_atomically(path: Path, text: str) -> None:
    write_bytes_atomically(path, text.encode("utf8"))


def write_bytes_atomically(path: Path, data: bytes) -> None:
    write_atomically(path, lambda file: file.write(data))


def process_alive(pid: int) -> bool:
    """Whether a process `pid` exists (another user's counts too)."""
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def remove_stale_partials(folder: Path) -> List[Path]:
    """Remove the temporary files in `folder` that processes no longer running left (a kill during a save); the
    files removed."""
    if not folder.is_dir():
        return []
    stale = []
    for path in folder.iterdir():
        match = PARTIAL_NAME.fullmatch(path.name)
        if match and not process_alive(int(match.group(1))):
            with contextlib.suppress(FileNotFoundError):
                path.unlink()
                stale.append(path)
    return stale
