"""Shared fixtures; shared helper functions live in tests/helpers.py."""

from __future__ import annotations

from pathlib import Path

import pytest
import torch


@pytest.fixture
def single_thread():
    """In-process training on one thread, as the training subprocesses run (SUBPROCESS_ENV)."""
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)


@pytest.fixture
def run_dir(tmp_path: Path) -> Path:
    return tmp_path / "outputs"
