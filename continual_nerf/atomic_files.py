"""Write-then-rename: a file under its final name is always complete, whenever the process is killed."""

from __future__ import annotations

import os
from pathlib import Path
from typing import BinaryIO, Callable, Optional


def write_atomically(path: Path, write: Callable[[BinaryIO], object], temporary_dir: Optional[Path] = None) -> None:
    """Call `write` on a temporary file in `temporary_dir` (default: beside `path`), then rename it to `path`."""
    folder = path.parent if temporary_dir is None else temporary_dir
    folder.mkdir(parents=True, exist_ok=True)
    path.parent.mkdir(parents=True, exist_ok=True)
    temporary = folder / f".{path.name}.partial-{os.getpid()}"
    try:
        with temporary.open("wb") as file:
            write(file)
            file.flush()
            os.fsync(file.fileno())  # the rename must not reach the disk before the data does
        os.replace(temporary, path)
    finally:
        temporary.unlink(missing_ok=True)


def write_text_atomically(path: Path, text: str) -> None:
    write_bytes_atomically(path, text.encode("utf8"))


def write_bytes_atomically(path: Path, data: bytes) -> None:
    write_atomically(path, lambda file: file.write(data))
