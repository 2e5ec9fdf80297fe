"""Crash-safe checkpoints: saved through atomic_files (renamed into place), loaded safely, with the RNG states.

A file is written under a temporary name and renamed into place, so a kill during a save leaves the
previous file (or none), never a truncated one. Checkpoints keep nerfstudio's names and keys, so
`ns-eval`, `ns-render` and `--load-dir` read them as usual; they also hold the RNG states, so a resumed
run draws the same rays as an uninterrupted one.
"""

from __future__ import annotations

import pickle
import random
import re
import zipfile
import zlib
from pathlib import Path
from typing import Any, Dict, Optional

import numpy as np
import torch

from continual_nerf.atomic_files import write_atomically
from continual_nerf.errors import CheckpointError, first_line

CHECKPOINT_NAME = re.compile(r"step-(\d+)\.ckpt")
"""nerfstudio's checkpoint file name; the number is the training step."""

CHECKPOINT_KEYS = ("step", "pipeline", "optimizers", "scalers")
"""Keys nerfstudio's Trainer needs to resume from a checkpoint."""
WEIGHTS_ONLY = "weights_only"
"""Key of a checkpoint that keeps the model's weights alone: a closed task's picture for ns-eval, ns-render and the
run viewer's task slider, not a point to resume from."""


def save_checkpoint_file(state: Dict[str, Any], path: Path) -> None:
    """torch.save `state` to `path` atomically; the temporary file lives in the run folder, not beside the
    checkpoints, because nerfstudio's loaders parse the name of every file in the checkpoint folder."""
    write_atomically(path, lambda file: torch.save(state, file), temporary_dir=path.parent.parent)


def checkpoint_steps(folder: Path) -> Dict[int, Path]:
    """Checkpoints in `folder` by step; other files are ignored."""
    found = (CHECKPOINT_NAME.fullmatch(path.name) for path in folder.iterdir())
    return {int(match.group(1)): folder / match.group(0) for match in found if match}


def find_checkpoint(load_dir: Path, load_step: Optional[int]) -> Path:
    """The checkpoint of `load_step` in `load_dir`, or its latest one; a one-line error when there is none."""
    if not load_dir.is_dir():
        raise CheckpointError(f"--load-dir {load_dir}: no such folder")
    steps = checkpoint_steps(load_dir)
    if not steps:
        raise CheckpointError(f"--load-dir {load_dir}: holds no step-*.ckpt checkpoint")
    if load_step is None:
        return steps[max(steps)]
    if load_step not in steps:
        raise CheckpointError(f"--load-step {load_step}: {load_dir} has checkpoints of steps {sorted(steps)}")
    return steps[load_step]


def verify_archive(path: Path) -> None:
    """Check every member of a checkpoint's zip archive against its CRC-32: torch.load reads tensors without doing
    so, and a flipped bit would go into the model and the replay oracle unnoticed."""
    if path.is_file() and not zipfile.is_zipfile(path):  # torch.save writes a zip archive; a cut one has no index
        raise CheckpointError(f"{path}: not a readable checkpoint (not a complete torch.save archive: truncated?)")
    try:
        with zipfile.ZipFile(path) as archive:
            corrupt = archive.testzip()
    except (OSError, EOFError, zipfile.BadZipFile, zlib.error, NotImplementedError) as error:
        raise CheckpointError(f"{path}: not a readable checkpoint ({first_line(error)})") from None
    if corrupt is not None:
        raise CheckpointError(
            f"{path}: corrupt checkpoint ({corrupt} does not match its CRC-32); resume from another with --load-step"
        )


def read_checkpoint(path: Path) -> Dict[str, Any]:
    """A checkpoint's content, its archive verified, unpickled with weights_only=True (tensors and plain containers
    only)."""
    verify_archive(path)
    try:
        state = torch.load(path, map_location="cpu", weights_only=True)
    except (OSError, RuntimeError, EOFError, pickle.UnpicklingError, zipfile.BadZipFile) as error:
        raise CheckpointError(f"{path}: not a readable checkpoint ({first_line(error)})") from None
    missing = [key for key in CHECKPOINT_KEYS if not isinstance(state, dict) or key not in state]
    if missing:
        raise CheckpointError(f"{path}: not a nerfstudio checkpoint (no {', '.join(missing)})")
    return state


def weights_only(state: Dict[str, Any], dropped_prefix: str) -> Dict[str, Any]:
    """`state` without what only resuming needs: the optimizers, schedulers, random states and the pipeline's keys that
    start with `dropped_prefix` (the replay oracle, which equals the model at a task's end)."""
    pipeline = {key: value for key, value in state["pipeline"].items() if not key.startswith(dropped_prefix)}
    return {
        "step": state["step"],
        "method": state.get("method"),
        "pipeline": pipeline,
        "optimizers": {},
        "schedulers": {},
        "scalers": state["scalers"],
        WEIGHTS_ONLY: True,
    }


def slim_checkpoint(path: Path, dropped_prefix: str) -> None:
    """Rewrite the checkpoint at `path` as `weights_only` (atomically: a kill leaves the whole one)."""
    save_checkpoint_file(weights_only(read_checkpoint(path), dropped_prefix), path)


def check_resumable(state: Dict[str, Any], path: Path, latest: Optional[Path]) -> None:
    """Refuse to resume or continue from a weights-only checkpoint: its optimizers and random states are gone."""
    if state.get(WEIGHTS_ONLY):
        newest = f"; load the latest, {latest.name}" if latest is not None and latest != path else ""
        raise CheckpointError(
            f"{path}: keeps the model's weights of a finished task only, not a run to resume or continue{newest}"
        )


def check_method(state: Dict[str, Any], path: Path, method_name: Optional[str]) -> None:
    """Refuse a checkpoint another method wrote: the run would change method midway."""
    saved = state.get("method")
    if saved == method_name:
        return
    if saved is None:
        raise CheckpointError(
            f"{path}: names no method (written before checkpoints named theirs), so it cannot be resumed as "
            f"{method_name}"
        )
    raise CheckpointError(f"{path}: a checkpoint of {saved}, not of {method_name}; resume it with ns-train {saved}")


def rng_states() -> Dict[str, Any]:
    """The states of every random number generator training draws from, in weights_only-loadable types."""
    _, keys, position, has_gauss, cached_gaussian = np.random.get_state(legacy=True)
    assert isinstance(keys, np.ndarray)
    return {
        "torch": torch.get_rng_state(),
        "cuda": torch.cuda.get_rng_state_all() if torch.cuda.is_available() else [],
        "numpy": [torch.from_numpy(keys.astype(np.int64)), position, has_gauss, cached_gaussian],
        "python": random.getstate(),
    }


def restore_rng_states(states: Dict[str, Any]) -> None:
    torch.set_rng_state(states["torch"])
    if states["cuda"] and torch.cuda.is_available():
        torch.cuda.set_rng_state_all(states["cuda"])
    keys, position, has_gauss, cached_gaussian = states["numpy"]
    np.random.set_state(("MT19937", keys.numpy().astype(np.uint32), position, has_gauss, cached_gaussian))
    random.setstate(states["python"])
