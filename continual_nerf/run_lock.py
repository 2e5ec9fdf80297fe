"""Claiming a run folder, so that one run at a time writes into it.

Checking that a folder holds no run and then writing config.yml races: two runs started at once both pass the check
and end up writing into the same folder. Instead the first run to create `.continual-run.lock` in it (O_EXCL) and
lock that file holds the folder until it ends; the file records the run's PID. The operating system drops the lock
when a process dies, however it dies, so a lock file a killed run left behind is taken over by the next run (which
says so) instead of blocking the folder forever; where the file system has no locks, the recorded PID is checked.
"""

from __future__ import annotations

import atexit
import contextlib
import fcntl
import os
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Dict, Optional

from continual_nerf.atomic_files import process_alive
from continual_nerf.errors import ContinualConfigError

LOCK_NAME = ".continual-run.lock"
"""The lock file in a run folder; it exists while a run holds the folder (or after a run was killed)."""


@dataclass
class RunLock:
    """A run folder this process holds."""

    path: Path
    descriptor: int

    def release(self) -> None:
        # removed before it is unlocked: a run waiting on this file then sees it is gone and creates its own
        with contextlib.suppress(OSError):
            self.path.unlink()
        os.close(self.descriptor)


_HELD: Dict[Path, RunLock] = {}
"""Run folders this process holds, by real path."""


def claim_run_folder(folder: Path) -> Optional[int]:
    """Hold `folder` for this process (creating it) until release_run_folder or exit; the PID of the killed run whose
    lock was taken over, if any. A folder another living run holds is a one-line ContinualConfigError."""
    key = folder.resolve()
    if key in _HELD:
        return None
    folder.mkdir(parents=True, exist_ok=True)
    path = folder / LOCK_NAME
    while True:
        try:
            descriptor = os.open(path, os.O_CREAT | os.O_EXCL | os.O_RDWR, 0o644)
            created = True
        except FileExistsError:
            try:
                descriptor = os.open(path, os.O_RDWR)
            except FileNotFoundError:  # released in between
                continue
            created = False
        try:
            holder = None if created else recorded_pid(descriptor)
            if not lock(descriptor, holder):
                holder = holder or written_pid(descriptor)
                process = "" if holder is None else f" (process {holder})"
                raise ContinualConfigError(
                    f"{folder} is in use by another run{process}; choose another --timestamp or --experiment-name, "
                    "or wait for that run to end"
                )
            if not same_file(descriptor, path):  # its holder released it between our open and our lock
                os.close(descriptor)
                continue
        except BaseException:
            os.close(descriptor)
            raise
        os.ftruncate(descriptor, 0)
        os.pwrite(descriptor, f"{os.getpid()}\n".encode(), 0)
        if not _HELD:
            atexit.register(release_all)
        _HELD[key] = RunLock(path, descriptor)
        return holder


def lock(descriptor: int, holder: Optional[int]) -> bool:
    """Lock the file without waiting; False when another process holds it. Without file locks (some network file
    systems), the recorded PID decides."""
    try:
        fcntl.flock(descriptor, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except BlockingIOError:
        return False
    except OSError:
        return holder is None or holder == os.getpid() or not process_alive(holder)
    return True


def recorded_pid(descriptor: int) -> Optional[int]:
    text = os.pread(descriptor, 32, 0).decode(errors="replace").strip()
    return int(text) if text.isdigit() else None


def written_pid(descriptor: int, seconds: float = 1.0) -> Optional[int]:
    """The PID a run that has just locked the file writes right after locking it; None if it never comes."""
    deadline = time.monotonic() + seconds
    while (holder := recorded_pid(descriptor)) is None and time.monotonic() < deadline:
        time.sleep(0.02)
    return holder


def same_file(descriptor: int, path: Path) -> bool:
    try:
        return os.stat(path).st_ino == os.fstat(descriptor).st_ino
    except FileNotFoundError:
        return False


def release_run_folder(folder: Path) -> None:
    """Let go of `folder` if this process holds it."""
    held = _HELD.pop(folder.resolve(), None)
    if held is not None:
        held.release()


def release_all() -> None:
    for folder in list(_HELD):
        release_run_folder(folder)
